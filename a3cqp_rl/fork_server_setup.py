"""The fork server's first import (`a3cqp_rl.worker_start`), for its effects on the server and so on every worker
forked from it:

* the server ends without the interpreter's teardown (`worker_exit`): it outlives the command by that second (torch,
  torchrl), holding the command's stdout and stderr open, so a pipe or `subprocess.run` reading them waited for it;
* torch on one thread, as every worker is, before any later import runs a torch op: then no OpenMP thread pool
  exists when a worker is forked (GNU OpenMP cannot use threads created before a fork).
"""

from a3cqp_rl import worker_exit

worker_exit.install()  # first: the exit handlers of what the server imports next run before it

import torch  # noqa: E402

torch.set_num_threads(1)
