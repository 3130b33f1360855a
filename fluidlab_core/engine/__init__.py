"""The simulation engine (Taichi): the Model (model.py), the State (state.py) and the Control (control.py); the
physics, each piece once (grid.py, transfer.py, constitutive.py, statics.py, tools.py, rigid.py, svd.py); the
fast and the differentiable solver (solver.py, diff_solver.py); the rollout loop (rollout.py) and gradient
checkpointing (checkpoint.py). docs/design.md §3 describes how they fit together."""
