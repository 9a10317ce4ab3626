"""Layer 4, the load path: model and state (:mod:`.model`), one step (:mod:`.step`), the step controller
(:mod:`.controller`), the drivers (:mod:`.simulate`), the public run (:mod:`.run`), batched sweeps
(:mod:`.sweep`) and progress reports (:mod:`.progress`)."""
