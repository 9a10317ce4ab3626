"""The run-directory checker (:mod:`jaxfric.io.contract`), section 4: ``contact.npz`` against the history
and the summary."""

from __future__ import annotations

import os
import zipfile

import numpy as np

from .contract_spec import (
    CLOSEST,
    END_OF,
    RTOL_NPZ,
    STEADY_TOL,
    TIME_TOL,
    close,
    is_int,
    scene_of,
)

__all__ = ["check_contact"]

# ---- 4. contact.npz -------------------------------------------------------------------------------

def check_contact(path: str, s: dict | None, cols: dict | None, out: list) -> None:
    p = os.path.join(path, "contact.npz")
    if not os.path.isfile(p) or os.path.getsize(p) == 0:
        return
    try:
        with np.load(p, allow_pickle=False) as f:
            data = {k: f[k] for k in f.files}
    except (ValueError, OSError, zipfile.BadZipFile) as err:
        out.append(f"contact.npz: cannot be read with allow_pickle=False ({err})")
        return
    top = {"instant_names": "U", "instant_steps": "int64", "instant_drawing_displacement": "float64",
           "x0": "float64", "elements": "int64", "tool_names": "U", "pair_node": "int64", "pair_tool": "int64"}
    for key, dtype in top.items():
        if key not in data:
            out.append(f"contact.npz: missing {key!r}")
        elif (data[key].dtype.kind != "U") if dtype == "U" else (data[key].dtype != np.dtype(dtype)):
            out.append(f"contact.npz: {key!r} has dtype {data[key].dtype}, expected {dtype}")
    if any(k not in data for k in top):
        return
    names = [str(n) for n in data["instant_names"]]
    k = len(names)
    x0, elements = data["x0"], data["elements"]
    n_tools, m = data["tool_names"].shape[0], data["pair_node"].shape[0]
    shapes = {"instant_names": (k,), "instant_steps": (k,), "instant_drawing_displacement": (k,),
              "tool_names": (n_tools,), "pair_node": (m,), "pair_tool": (m,)}
    ok = True
    for key, shape in shapes.items():
        if data[key].shape != shape:
            out.append(f"contact.npz: {key!r} has shape {data[key].shape}, expected {shape}")
            ok = False
    if x0.ndim != 2 or x0.shape[1] != 2 or elements.ndim != 2 or elements.shape[1] not in (4, 6):
        out.append(f"contact.npz: x0 {x0.shape} / elements {elements.shape} must be (n_nodes, 2) / (n_el, 4), "
                   f"or (n_el, 6) on elements quadratic along the strip")
        return
    n_nodes, n_el = x0.shape[0], elements.shape[0]
    # Six-node elements (element_order=2): node columns 0 .. 2 nx and a padding column, numbered as the spec's
    # section 0 numbers the bilinear ones; each element's nodes counter-clockwise through its mid-side nodes.
    order = elements.shape[1] // 2 - 1
    if not np.all(np.isfinite(x0)):
        out.append("contact.npz: x0 has non-finite values")
    if s is not None and isinstance(s.get("mesh"), list) and len(s["mesh"]) == 2:
        nx, ny = s["mesh"]
        if is_int(nx) and is_int(ny) and (order * (nx + 1) * (ny + 1), nx * ny) == (n_nodes, n_el):
            i_grid, j_grid = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
            i, j = order * i_grid.ravel(), j_grid.ravel()
            node = lambda a, b: a * (ny + 1) + b  # noqa: E731
            along = range(order + 1)
            expected = np.stack([node(i + k, j) for k in along] + [node(i + order - k, j + 1) for k in along],
                                axis=1)
            if not np.array_equal(elements, expected):
                out.append("contact.npz: elements do not follow the numbering of benchmarks spec section 0")
        else:
            out.append(f"contact.npz: {n_nodes} nodes / {n_el} elements do not match mesh {s['mesh']}")
    if n_el and np.all(elements >= 0) and np.all(elements < n_nodes):
        q = x0[elements]
        x, y = q[:, :, 0], q[:, :, 1]  # shoelace formula: positive area = counter-clockwise
        area = 0.5 * np.sum(x * np.roll(y, -1, axis=1) - np.roll(x, -1, axis=1) * y, axis=1)
        if np.any(area <= 0):
            out.append("contact.npz: elements must be counter-clockwise in x0")
    else:
        out.append("contact.npz: element node indices out of range")
    if np.any((data["pair_node"] < 0) | (data["pair_node"] >= n_nodes)):
        out.append("contact.npz: pair_node out of range")
    if np.any((data["pair_tool"] < 0) | (data["pair_tool"] >= n_tools)):
        out.append("contact.npz: pair_tool out of range")
        ok = False
    scene = scene_of(s.get("scene")) if s is not None else None
    tools = [str(t) for t in data["tool_names"]]
    if scene is not None:
        allowed = [scene["tools"]] + ([scene["tools"] + scene["extra_tools"]] if "extra_tools" in scene else [])
        if tuple(tools) not in allowed:
            out.append(f"contact.npz: tool_names {tools} must be " + " or ".join(str(list(a)) for a in allowed))
    if s is not None and isinstance(s.get("instants"), list) and names != s["instants"]:
        out.append(f"contact.npz: instant_names {names} differ from summary instants {s['instants']}")
    per = {"x": ((n_nodes, 2), "float64"), "eqps": ((n_el,), "float64"), "rn": ((m,), "float64"),
           "rt": ((m,), "float64"), "normal": ((m, 2), "float64"), "gap": ((m,), "float64"),
           "mu": ((m,), "float64"), "status": ((m,), "int8"), "tool_offset": ((n_tools, 2), "float64")}
    for name in names:
        complete = True
        for key, (shape, dtype) in per.items():
            full = f"{name}__{key}"
            if full not in data:
                out.append(f"contact.npz: missing {full!r}")
                complete = False
            elif data[full].dtype != np.dtype(dtype) or data[full].shape != shape:
                out.append(f"contact.npz: {full!r} is {data[full].dtype} {data[full].shape}, expected "
                           f"{dtype} {shape}")
                complete = False
            elif dtype == "float64" and not np.all(np.isfinite(data[full])):
                out.append(f"contact.npz: {full!r} has non-finite values")
                complete = False
        if complete and ok:
            _check_instant(data, name, names.index(name), s, cols, scene, tools, out)


def _check_instant(data, name, i, s, cols, scene, tools, out) -> None:
    rn, rt, mu = data[f"{name}__rn"], data[f"{name}__rt"], data[f"{name}__mu"]
    normal, gap, status = data[f"{name}__normal"], data[f"{name}__gap"], data[f"{name}__status"]
    where = f"contact.npz: instant {name!r}"
    if np.any(rn < -1e-9):
        out.append(f"{where}: rn < 0")
    if np.any(mu < 0):
        out.append(f"{where}: mu < 0")
    if np.any(gap > 1e30):
        out.append(f"{where}: gap above 1e30")
    length = np.linalg.norm(normal, axis=1)
    if np.any((np.abs(length - 1.0) > 1e-9) & (length != 0.0)):
        out.append(f"{where}: normal is neither a unit vector nor (0, 0)")
    if np.any((status < 0) | (status > 2)):
        out.append(f"{where}: status outside {{0, 1, 2}}")
    closed = rn > 1e-9
    expected = np.where(closed, np.where(np.abs(rt) < (1.0 - 1e-6) * mu * rn, 1, 2), 0)
    wrong = np.flatnonzero(expected != status)
    if wrong.size:
        p = int(wrong[0])
        out.append(f"{where}: status disagrees with rn, rt, mu (benchmarks spec section 0) at "
                   f"{wrong.size} pairs, e.g. pair {p}: status {int(status[p])}, rn {rn[p]:.6g}, "
                   f"rt {rt[p]:.6g}, mu {mu[p]:.6g}")
    if cols is None:
        return
    n = len(cols["step"])
    step = int(data["instant_steps"][i])
    if not 0 <= step < n:
        out.append(f"{where}: step {step} outside the history (0..{n - 1})")
        return
    if not close(float(data["instant_drawing_displacement"][i]), cols["drawing_displacement"][step]):
        out.append(f"{where}: instant_drawing_displacement differs from history.csv at step {step}")
    n_active, n_slip = int(np.sum(status > 0)), int(np.sum(status == 2))
    if n_active != cols["n_active"][step] or n_slip != cols["n_slip"][step]:
        out.append(f"{where}: {n_active} active / {n_slip} slip pairs, history.csv step {step} has "
                   f"{cols['n_active'][step]} / {cols['n_slip'][step]}")
    if scene is not None and scene["clamp"][0] in tools:
        k = tools.index(scene["clamp"][0])
        e_q = np.asarray(scene["clamp"][1])
        t = np.stack([-normal[:, 1], normal[:, 0]], axis=1)
        f = rn[:, None] * normal + rt[:, None] * t
        proj = (f @ e_q)[data["pair_tool"] == k]
        total, expected_f = float(np.sum(proj)), cols["clamping_force"][step]
        scale = max(abs(expected_f), float(np.sum(np.abs(proj))))
        if abs(total - expected_f) > RTOL_NPZ * scale + 1e-9:
            out.append(f"{where}: clamping force from the pairs {total:.9g} N/mm, history.csv step {step} "
                       f"has {expected_f:.9g}")
    # Instant rules that are plain functions of the history.
    phases = cols["phase"]
    fallback = s.get("instants_fallback", []) if s is not None else []
    if name == "final" and step != n - 1:
        out.append(f"{where}: 'final' must be the last step {n - 1}, got {step}")
    if name in fallback and step != n - 1:
        out.append(f"{where}: a fallback instant must be at the last step {n - 1}")
    if scene is not None and name in END_OF:
        k = scene["phases"].index(END_OF[name]) + 1
        if phases[step] != END_OF[name] or abs(cols["time"][step] - k) > TIME_TOL:
            out.append(f"{where}: must be the end of phase {END_OF[name]!r} (time {k}), got step {step}")
    key = (s.get("scene") if s is not None else None, name)
    if key in CLOSEST:
        draw = [j for j, p in enumerate(phases) if p == "draw"]
        best = min(draw, key=lambda j: abs(cols["drawing_displacement"][j] - CLOSEST[key]), default=None)
        if best is not None and abs(cols["drawing_displacement"][step] - CLOSEST[key]) > \
                abs(cols["drawing_displacement"][best] - CLOSEST[key]) + STEADY_TOL:
            out.append(f"{where}: not the draw step with drawing displacement closest to {CLOSEST[key]} mm")
