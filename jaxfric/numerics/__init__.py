"""Layer 1, numerics: structured linear solves (:mod:`.linalg`), the one Newton loop with its implicit
derivative (:mod:`.newton`), result codes (:mod:`.results`), kink-safe tensor helpers (:mod:`.tensor`),
input checks and a bounded cache. Nothing here knows about strips or contact."""
