"""Controller plugins: failproof torque-off, emergency controllers, PD, trajectories."""
