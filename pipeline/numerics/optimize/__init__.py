"""The nominal trajectories' optimal control (paper §IV-A): cost, penalties, margins, gradient
(sensitivities and adjoint), descent, shooting and the horizon search."""
