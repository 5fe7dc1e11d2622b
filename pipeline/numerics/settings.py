"""Names and defaults of the numerical options, set once here and read everywhere else.

Standard library only, so that the command line can offer the choices without loading the
numerics. The margins are the paper's §IV-A ones (units of the constraint they widen):
Unsafe is bloated by ``d + eps_d``, Goal shrunk by ``d + eps_g`` (m) and the input bounds by
``eps_i`` (input units).
"""

from __future__ import annotations

EPS_D = 0.05  # eq. (42): d' = d + eps_d
EPS_G = 0.05  # eq. (41): ModGoal = Goal shrunk by d + eps_g
EPS_I = 0.0  # eq. (40): input bounds shrunk by eps_i

DESCENT_METHODS = ("gd", "lbfgs")  # the paper's gradient descent, or L-BFGS-B
HORIZON_SEARCHES = ("continuation", "bisection")  # how the final time is shortened (Remark 4)
# The certificate kinds (the scenario's `certificate`, --certificate): one contraction metric P
# and gain K for all time (eq. (10)-(12)), or a time-varying funnel K[k], P[k] per trajectory.
CERTIFICATES = ("constant", "funnel")
