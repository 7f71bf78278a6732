"""Trajectory optimisation: shooting problems, iLQR and DDP, their derivatives, MPC."""
