"""Result codes: failures are values inside ``jit`` and become exceptions at the public entry point."""

from __future__ import annotations

import enum

__all__ = ["Result", "SimulationError", "describe", "causes", "band_widening"]


class Result(enum.IntEnum):
    CONTINUE = -1          # internal: Newton loop still iterating
    SUCCESS = 0
    MAX_ITERATIONS = 1     # Newton did not converge in max_iterations
    NONFINITE = 2          # a NaN or Inf appeared in the residual or the tangent
    INVERTED_ELEMENT = 3   # det F <= 0 at a Gauss point or an element centroid
    MAX_STEPS = 4          # the history buffer is full before the end of the load path
    AUGMENTATIONS = 6      # the augmented Lagrangian did not reach its target gap
    LCP_FAILED = 7         # the exact contact problem of an iterate had no solution (Lemke ray)
    CONTACT_BAND = 8       # a candidate outside the proximity band of exact contact penetrates a tool
    STOPPED = 9            # a stop request ended the run between two chunks of steps (resumable)
    PRESELECTION = 10      # a candidate the step's pair pre-selection left out could have reached its tool
    STALLED = 11           # consecutive steps crawled at the smallest increment (StepControl.stall_steps)
    BAND_FULL = 12         # an attempt ended on CONTACT_BAND: the band is too small for the contact zone


_ADVICE = {
    Result.SUCCESS: "converged",
    Result.MAX_ITERATIONS: "Newton did not converge within the iteration limit; reduce the nominal "
                           "step (more n_steps) or raise NewtonOptions.max_iterations",
    Result.NONFINITE: "a non-finite value (NaN/Inf) appeared in the residual or the tangent; reduce the "
                      "nominal step and check the material and load parameters",
    Result.INVERTED_ELEMENT: "an element inverted (det F <= 0); reduce the nominal step or refine the mesh "
                             "where the deformation concentrates",
    Result.MAX_STEPS: "the history buffer is full before the end of the load path; raise "
                      "StepControl.max_steps (a scene's config field max_steps: --set max_steps=N)",
    Result.AUGMENTATIONS: "the augmented Lagrangian needed more augmentations than allowed to reach its "
                          "target gap; raise eps_n, the target_gap or max_augmentations, or reduce the step",
    Result.LCP_FAILED: "the linearised contact problem had no solution (Lemke ray termination); reduce the "
                       "nominal step",
    Result.CONTACT_BAND: "a candidate node outside the proximity band of the exact contact solver penetrates "
                         "a tool; raise Complementarity.band (or leave it None: all candidates)",
    Result.PRESELECTION: "a candidate node left out of the step's pair pre-selection could have reached its tool "
                         "(it moved further than its clearance allows even at the smallest increment); raise "
                         "the tool's capacity (RigidTool.capacity), or switch the pre-selection off "
                         "(--set preselect=false)",
    Result.BAND_FULL: "a step's attempt left a penetrating candidate node out of the exact contact "
                      "solver's proximity band: the contact zone outgrew the band; the chunked driver "
                      "(jaxfric.loadpath.run.run, the command line) widens it and goes on, a whole-run program "
                      "stops here: raise Complementarity.band (a scene's config field band)",
    Result.STALLED: "the run crawls: step after step took the smallest increment after failed attempts and "
                    "the increment did not grow back (StepControl.stall_steps, a scene's config field "
                    "stall_steps); change the algorithm, the contact law or the nominal step, or raise "
                    "stall_steps to let it crawl on",
}


def describe(code: int) -> str:
    return _ADVICE.get(Result(int(code)), f"unknown result code {int(code)}")


def causes(mask: int) -> list[str]:
    """The result codes set in a step's ``cut_codes`` bit mask (bit k: an attempt ended with Result k),
    by name, in code order: ``max_iterations``, ``contact_band``, ... ; ``stage`` for bit 0, a converged
    continuation stage before the last (an attempt that is not the accepted step without failing)."""
    mask = int(mask)
    return ["stage" if code == Result.SUCCESS else code.name.lower()
            for code in Result if code >= 0 and mask >> int(code) & 1]


def band_widening(t: float, band: int | None) -> str:
    """One widening of exact contact's proximity band after ``BAND_FULL`` (``RunResult.band_widened``) in
    words: "to 512 nodes at t = 2.4"."""
    return f"to {'every candidate node' if band is None else f'{band} nodes'} at t = {t:.6g}"


class SimulationError(RuntimeError):
    """A simulation stopped before the end of its load path.

    Attributes:
        code: the :class:`Result` of the last attempt.
        result: the partial result: everything converged up to the failure.
    """

    def __init__(self, message: str, code: Result, result=None):
        super().__init__(message)
        self.code = code
        self.result = result
