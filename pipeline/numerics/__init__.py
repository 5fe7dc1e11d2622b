"""Numerical methods on the model, by concept: ``tube/`` (the constant contraction certificate),
``funnel/`` (the time-varying one), ``terminal/`` (the controller inside Goal), ``optimize/``
(the nominal trajectories), ``verify/`` (the independent checks), ``closed_loop/`` (simulation
and falsification); ``hull``, ``uncertainty``, ``prechecks``, ``settings`` and the compiled
``kernels/`` serve them all."""
