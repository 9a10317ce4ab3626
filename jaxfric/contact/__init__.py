"""Layer 3, contact of the strip with rigid tools: tool geometry (:mod:`.tools`), tools as contact
bodies and their pairs (:mod:`.rigid`), the one open/stick/slip rule (:mod:`.status`), the per-pair laws
(:mod:`.laws`), the step's system (:mod:`.system`), the contact formulations (:mod:`.formulations`) and
exact contact: the complementarity problem (:mod:`.lcp`), Lemke (:mod:`.lemke`, :mod:`.complementary_basis`),
semismooth Newton (:mod:`.alart_curnier`) and the in-loop solver (:mod:`.exact` and its ``exact_*`` parts)."""
