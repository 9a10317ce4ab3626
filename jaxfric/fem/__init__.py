"""Layer 2, the finite-element discretisation of the strip: mesh (:mod:`.mesh`), element (:mod:`.element`),
material (:mod:`.material`, with back stresses :mod:`.kinematic`), global assembly (:mod:`.assembly`) and
prescribed loading (:mod:`.loading`)."""
