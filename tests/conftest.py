import torch

torch.set_num_threads(1)  # CI has 2 cores shared by everything; single-thread torch is faster for tiny ops
