"""Hyper-parameter and controller tuning on pygad: the Table V GA (ga.py) and NSGA-II (nsga2.py), sharing one
generation loop with checkpoints, an evaluation log and worker pools (runner.py, pool.py)."""
