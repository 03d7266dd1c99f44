"""The package's C sources and their compiler flags: read by setup.py (no imports here, so it loads in the build
environment) and by `a3cqp_rl.native_build` at run time."""

COMMON_FLAGS = ("-std=c99", "-O3")
"""No -ffast-math (IEEE semantics: reductions are not reassociated) and no -march=native (results must not depend on
the machine that built the library).  -O3 vectorises the QP's axpy loops (controller's QP at B = 64: 716 → 500 µs
per batch against -O2)."""

NATIVE_SOURCES = {
    "a3cqp_rl/qp/native/gi_qp.c": (),  # also a CPython extension module (_gi_qp: solve, vjp), loaded by a3cqp_rl.qp.native
    "a3cqp_rl/control/native/a3cqp_step.c": (),
    "a3cqp_rl/robot/native/contact_filter.c": (),
    "a3cqp_rl/robot/native/sense.c": (),
    "algorithms/native/a2c_iteration.c": ("-fopenmp-simd", "-fno-math-errno", "-ffp-contract=off"),
    "envs/native/point_mass.c": ("-fno-math-errno",),
    "envs/native/hand.c": (),
    "envs/native/period.c": (),
    "envs/native/tick.c": (),
}
"""Every C source (path from the project root) and its extra flags; each builds into `dir/_stem<ext suffix>`."""

NATIVE_HEADERS = {
    "algorithms/native/a2c_iteration.c": ("envs/native/point_mass.h",),
    "envs/native/point_mass.c": ("envs/native/point_mass.h",),
}
"""Project headers a source includes (their folders go to the compiler as -I; editing one rebuilds the library)."""
