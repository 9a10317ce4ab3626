"""Layer 5, input and output: the run directory (:mod:`.output`), its named instants (:mod:`.instants`),
the independent checker (:mod:`.contract`), figures (:mod:`.figures`, :mod:`.plotting`) and batches of
runs into directories (:mod:`.batch`)."""
