"""Layer 5, identification: scene values as differentiable inputs (:mod:`.params`), fitting to measured
curves (:mod:`.fit` and its ``fit_*`` parts) and the error-against-run-time report (:mod:`.accuracy`)."""
