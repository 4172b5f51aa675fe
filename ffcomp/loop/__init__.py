"""The model loop: identify, validate, diagnose, fit (model versus measurement).

* :mod:`.identify` -- the paper's two-sweep identification (Eq. 22, Eqs. 26-34), bounded;
* :mod:`.validate` -- goodness of fit per measurement, band, pose and axis;
* :mod:`.diagnose` -- which effect is missing (held-out scores by pose);
* :mod:`.evidence` -- the residual's signatures in words;
* :mod:`.fit` -- fitting effect parameters (and the base dynamics) to measured FRFs;
* :mod:`.metrics` -- R^2 (Eq. 36) and the normalised complex residual.
"""
