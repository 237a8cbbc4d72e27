"""Identity (classification) fusion: Bayes and Dempster-Shafer (Challa & Koks, seed 004).

Pure numpy, no I/O. Equation numbers are those of Challa & Koks, "Bayesian and Dempster-Shafer
fusion" (``shared/seeds/004_e832512ceaf07c5b.txt``).

Evidence combination (re-exported by the public façade :mod:`fusionlog.identity`):

* :mod:`.bayes`     Bayes' rule for several sensors, eqs. (35)-(41)
* :mod:`.dempster`  Dempster's rule (eq. 47), belief and plausibility on power-set arrays
* :mod:`.masses`    the same on ``{frozenset: mass}`` dicts, and conversions to and from arrays

The identity kind of a scenario:

* :mod:`.model`     ``IdentitySensor``, ``IdentitySystem`` (the kind's "System")
* :mod:`.simulate`  true classes and reports, chunked random streams shared with the state kind
* :mod:`.fusion`    BAYES and DS estimates of blocks of runs, decisions, the estimate columns
* :mod:`.metrics`   ``IdentityMetrics``: accuracy, log-loss, belief, conflict, disagreement
"""
