"""Small QP test problems from other projects' suites and the failure families a solver must flag.

Each problem is rebuilt here from its published definition (the numbers are the problems', the code
is ours): qpsolvers' test problems (QPSUT01-05, the dense and infeasible problems of its solve_qp tests,
qpmad's demo, the infinite-inequality and unbounded-below problems), small Maros-Meszaros problems
from their Hock-Schittkowski definitions (HS21, HS35, HS51, HS52, HS53, HS76, TAME, ZECEVIC2, GENHS28,
QPTEST), ProxSuite's random generators (strongly convex, degenerate, not strongly convex, box
constrained, unconstrained; two-sided rows with ±1e20 as "no bound"), and families of LPs, singular,
degenerate, equality-heavy, infeasible, unbounded, ill-scaled, non-convex and invalid problems.

`reference(problem)` solves one with cvxpy + Clarabel (tight tolerances) for the expected status and
optimal value; problems whose answer is a matter of definition (non-convex P, NaN data, wrong-sign
infinities) carry it in `expect`.  `companion(problem)` is a well-posed QP of the same sizes, to check
that one instance's failure leaves the rest of its batch alone.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from a3cqp_rl.qp.status import QPStatus

__all__ = ["QPProblem", "peer_problems", "reference", "companion", "objective", "max_violation", "NO_BOUND",
           "RANDOM_FAMILIES", "random_problem"]

NO_BOUND = 1e20
"""|bound| at and above which a bound or right-hand side means "none" (peers write 1e20 for it)."""

_INF = np.inf


@dataclass
class QPProblem:
    """min ½xᵀPx + qᵀx s.t. Ax = b, Gx ≤ h, lb ≤ x ≤ ub (numpy float64, unbatched; absent parts None)."""

    name: str
    family: str
    P: np.ndarray
    q: np.ndarray
    A: np.ndarray | None = None
    b: np.ndarray | None = None
    G: np.ndarray | None = None
    h: np.ndarray | None = None
    lb: np.ndarray | None = None
    ub: np.ndarray | None = None
    expect: QPStatus | None = None
    """Expected status when it is a matter of definition (else the reference solver's)."""
    source: str = ""
    tags: tuple[str, ...] = field(default=())

    @property
    def n(self) -> int:
        """Number of variables."""
        return int(self.q.shape[0])

    def args(self) -> tuple[np.ndarray | None, ...]:
        """(P, q, A, b, G, h, lb, ub) for `solve_qp`."""
        return self.P, self.q, self.A, self.b, self.G, self.h, self.lb, self.ub


def objective(p: QPProblem, x: np.ndarray) -> float:
    """½xᵀPx + qᵀx."""
    return float(0.5 * x @ p.P @ x + p.q @ x)


def max_violation(p: QPProblem, x: np.ndarray) -> float:
    """Largest constraint violation of x, each row relative to 1 + |rhs| + Σ|row·x| (bounds ≥ 1e20: none)."""
    worst = 0.0

    def rel(v: np.ndarray, rhs: np.ndarray, terms: np.ndarray) -> float:
        return float(np.max(v / (1.0 + np.abs(rhs) + terms), initial=0.0))

    if p.A is not None:
        worst = max(worst, rel(np.abs(p.A @ x - p.b), p.b, np.abs(p.A) @ np.abs(x)))
    if p.G is not None:
        keep = p.h < NO_BOUND
        worst = max(worst, rel((p.G @ x - p.h)[keep], p.h[keep], (np.abs(p.G) @ np.abs(x))[keep]))
    for bound, sign in ((p.lb, -1.0), (p.ub, 1.0)):
        if bound is not None:
            keep = np.abs(bound) < NO_BOUND
            worst = max(worst, rel((sign * (x - bound))[keep], bound[keep], np.abs(x)[keep]))
    return worst


# ------------------------------------------------------------------------------------------------
# qpsolvers' test problems (tests/problems.py, qpsolvers/problems.py, tests/test_solve_qp.py)
# ------------------------------------------------------------------------------------------------


def _qpsolvers() -> list[QPProblem]:
    M = np.array([[1.0, 2.0, 0.0], [-8.0, 3.0, 2.0], [0.0, 1.0, 1.0]])
    P3, q3 = M.T @ M, np.array([3.0, 2.0, 3.0]) @ M
    G3, h3 = np.array([[1.0, 2.0, 1.0], [2.0, 0.0, 1.0], [-1.0, 2.0, -1.0]]), np.array([3.0, 2.0, -2.0])
    A3, b3 = np.ones((1, 3)), np.array([1.0])
    M4 = np.array([[1.0, -2.0, 0.0, 8.0], [-6.0, 3.0, 1.0, 4.0], [-2.0, 1.0, 0.0, 1.0], [9.0, 9.0, 5.0, 3.0]])
    P4, q4 = M4.T @ M4, np.array([-3.0, 2.0, 0.0, 9.0]) @ M4
    src = "qpsolvers"
    out = [
        QPProblem("qpsut01", "published", P3, q3, A3, b3, np.array([[4.0, 2.0, 0.0], [-1.0, 2.0, -1.0]]),
                  np.array([1.0, -2.0]), np.array([-0.5, -0.4, -0.5]), np.ones(3), source=src),
        QPProblem("qpsut02", "published", P4, q4, np.array([[1.0, 1, 1, 1], [1.0, -1, -1, 1]]), np.array([10.0, 0.0]),
                  np.array([[4.0, 7.0, 0.0, -2.0]]), np.array([30.0]), np.array([-2.0, -1.0, -3.0, 1.0]),
                  np.array([4.0, 2.0, 6.0, 10.0]), source=src),
        QPProblem("qpsut03 (partial infinite bounds)", "published", P4, q4, lb=np.array([-_INF, -0.4, -_INF, -1.0]),
                  ub=np.array([_INF, _INF, 0.5, 1.0]), source=src),
        QPProblem("qpsut04", "published", np.eye(3), 0.01 * np.ones(3), np.ones((1, 3)), np.ones(1), np.eye(3),
                  np.ones(3), source=src),
        QPProblem("qpsut05 (no constraints, n = 1)", "published", np.array([[2.0]]), np.array([-2.0]), source=src),
        QPProblem("qptest (Maros-Meszaros)", "published", np.array([[8.0, 2.0], [2.0, 10.0]]), np.array([1.5, -2.0]),
                  G=np.array([[-1.0, 2.0], [-2.0, -1.0]]), h=np.array([6.0, -2.0]), lb=np.zeros(2),
                  ub=np.array([20.0, _INF]), source=src),
        QPProblem("dense sd3310", "published", P3, q3, A3, b3, G3, h3, source=src),
        QPProblem("dense, one inequality", "published", P3, q3, A3, b3, G3[1:2], h3[1:2], source=src),
        QPProblem("dense, no equality", "published", P3, q3, G=G3, h=h3, source=src),
        QPProblem("dense, no inequality", "published", P3, q3, A3, b3, source=src),
        QPProblem("dense, no constraint", "published", P3, q3, source=src),
        QPProblem("dense, bounds", "published", P3, q3, A3, b3, G3, h3, -0.6 * np.ones(3), 0.7 * np.ones(3), source=src),
        QPProblem("infinite inequality (h = +inf)", "published", P3, q3, A3, b3,
                  np.array([[4.0, 2.0, 0.0], [-1.0, 2.0, -1.0]]), np.array([_INF, -2.0]),
                  np.array([-0.5, -0.4, -0.5]), np.ones(3), source=src),
        QPProblem("unfeasible (Ax = 42)", "infeasible", P3, q3, A3, np.array([42.0]),
                  np.array([[1.0, 1.0, 1.0], [2.0, 0.0, 1.0], [-1.0, 2.0, -1.0]]), h3, source=src),
    ]
    # qpmad's demo: equal bounds on four variables.
    lb = np.array([1.0, 2.0, 3.0, 4.0] + [-5.0] * 16)
    ub = np.array([1.0, 2.0, 3.0, 4.0] + [0.5] * 16)
    out.append(QPProblem("qpmad demo (equal bounds)", "degenerate", np.eye(20), np.ones(20),
                         G=np.vstack([np.ones((1, 20)), -np.ones((1, 20))]), h=np.array([1.5, 1.5]), lb=lb, ub=ub,
                         source="qpsolvers (qpmad demo.cpp)"))
    # Sparse infeasible problem of qpsolvers' tests (tridiagonal P, x ≤ −2 against 0.5 ≤ x), at n = 40.
    n = 40
    Mt = np.eye(n) + np.diag(np.r_[0.0, -np.ones(n - 2)], 1) + np.diag(np.r_[np.ones(n - 2), 0.0], -1)
    out.append(QPProblem("sparse unfeasible (n = 40)", "infeasible", Mt @ Mt.T, -np.ones(n), G=-np.eye(n),
                         h=-2.0 * np.ones(n), lb=0.5 * np.ones(n), ub=1.5 * np.ones(n), source=src))
    v = np.array([5.4, -1.2, -1e-2, 1e4])
    out.append(QPProblem("unbounded below (P = vvᵀ)", "unbounded", np.outer(v, v), np.array([-1.0, -2.0, 0.0, 3e-4]),
                         source=src))
    return out


# ------------------------------------------------------------------------------------------------
# Small Maros-Meszaros problems, from their Hock-Schittkowski / CUTE definitions
# ------------------------------------------------------------------------------------------------


def _maros_meszaros() -> list[QPProblem]:
    src = "Maros-Meszaros"
    out = [
        # HS21: min 0.01 x1² + x2² − 100, 10 x1 − x2 ≥ 10, 2 ≤ x1 ≤ 50, −50 ≤ x2 ≤ 50.
        QPProblem("HS21", "published", np.diag([0.02, 2.0]), np.zeros(2), G=np.array([[-10.0, 1.0]]),
                  h=np.array([-10.0]), lb=np.array([2.0, -50.0]), ub=np.array([50.0, 50.0]), source=src),
        # HS35: min 9 − 8x1 − 6x2 − 4x3 + 2x1² + 2x2² + x3² + 2x1x2 + 2x1x3, x1 + x2 + 2x3 ≤ 3, x ≥ 0.
        QPProblem("HS35", "published", np.array([[4.0, 2.0, 2.0], [2.0, 4.0, 0.0], [2.0, 0.0, 2.0]]),
                  np.array([-8.0, -6.0, -4.0]), G=np.array([[1.0, 1.0, 2.0]]), h=np.array([3.0]), lb=np.zeros(3),
                  source=src),
        # HS76: four variables, three inequalities, x ≥ 0.
        QPProblem("HS76", "published",
                  np.array([[2.0, 0.0, -1.0, 0.0], [0.0, 1.0, 0.0, 0.0], [-1.0, 0.0, 2.0, 1.0], [0.0, 0.0, 1.0, 1.0]]),
                  np.array([-1.0, -3.0, 1.0, -1.0]),
                  G=np.array([[1.0, 2.0, 1.0, 1.0], [3.0, 1.0, 2.0, -1.0], [0.0, -1.0, -4.0, 0.0]]),
                  h=np.array([5.0, 4.0, -1.5]), lb=np.zeros(4), source=src),
        # TAME: min (x − y)², x + y = 1, x, y ≥ 0 (P singular).
        QPProblem("TAME (singular P)", "singular P", np.array([[2.0, -2.0], [-2.0, 2.0]]), np.zeros(2),
                  A=np.ones((1, 2)), b=np.ones(1), lb=np.zeros(2), source=src),
        # ZECEVIC2: min −2x1 − 3x2 + 2x2², x1 + x2 ≤ 2, x1 + 4x2 ≤ 4, 0 ≤ x ≤ 10 (P singular).
        QPProblem("ZECEVIC2 (singular P)", "singular P", np.diag([0.0, 4.0]), np.array([-2.0, -3.0]),
                  G=np.array([[1.0, 1.0], [1.0, 4.0]]), h=np.array([2.0, 4.0]), lb=np.zeros(2), ub=10 * np.ones(2),
                  source=src),
    ]
    # HS51/52/53: five variables, three equalities (HS53 with bounds ±10).
    A = np.array([[1.0, 3.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 1.0, -2.0], [0.0, 1.0, 0.0, 0.0, -1.0]])

    def sq_terms(c1: float) -> tuple[np.ndarray, np.ndarray]:
        # (c1·x1 − x2)² + (x2 + x3 − 2)² + (x4 − 1)² + (x5 − 1)², as ½xᵀPx + qᵀx (+ const).
        R = np.array([[c1, -1.0, 0, 0, 0], [0, 1.0, 1.0, 0, 0], [0, 0, 0, 1.0, 0], [0, 0, 0, 0, 1.0]])
        r = np.array([0.0, 2.0, 1.0, 1.0])
        return 2 * R.T @ R, -2 * R.T @ r

    P51, q51 = sq_terms(1.0)
    P52, q52 = sq_terms(4.0)
    out += [
        QPProblem("HS51", "equality-heavy", P51, q51, A, np.array([4.0, 0.0, 0.0]), source=src),
        QPProblem("HS52", "equality-heavy", P52, q52, A, np.zeros(3), source=src),
        QPProblem("HS53", "equality-heavy", P51, q51, A, np.zeros(3), lb=-10 * np.ones(5), ub=10 * np.ones(5), source=src),
    ]
    # GENHS28: Σ (x_i + x_{i+1})² over ten variables (P singular), x_i + 2x_{i+1} + 3x_{i+2} = 1.
    n = 10
    R = np.zeros((n - 1, n))
    for i in range(n - 1):
        R[i, i] = R[i, i + 1] = 1.0
    Aeq = np.zeros((n - 2, n))
    for i in range(n - 2):
        Aeq[i, i : i + 3] = [1.0, 2.0, 3.0]
    out.append(QPProblem("GENHS28 (singular P)", "singular P", 2 * R.T @ R, np.zeros(n), Aeq, np.ones(n - 2), source=src))
    return out


# ------------------------------------------------------------------------------------------------
# ProxSuite's random problem generators (test/src utilities), rebuilt with our own seeds
# ------------------------------------------------------------------------------------------------


def _sparse_rand(rng: np.random.Generator, rows: int, cols: int, density: float) -> np.ndarray:
    mask = rng.uniform(size=(rows, cols)) < density
    out = np.zeros((rows, cols))
    out[mask] = rng.standard_normal(int(mask.sum()))
    return out


def _sparse_pd(rng: np.random.Generator, n: int, rho: float, density: float) -> np.ndarray:
    H = _sparse_rand(rng, n, n, density / 2)
    H = 0.5 * (H + H.T)
    H[np.diag_indices(n)] += rho + abs(np.linalg.eigvalsh(H).min())
    return H


def _two_sided(C: np.ndarray, lo: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """lo ≤ Cx ≤ up as [C; −C] x ≤ [up; −lo] (a −1e20 lower side becomes a 1e20 right-hand side: no row)."""
    return np.vstack([C, -C]), np.concatenate([up, -lo])


def _proxsuite() -> list[QPProblem]:
    src = "ProxSuite generators"
    out = []
    for k, (n, n_eq, n_in) in enumerate([(10, 2, 5), (16, 4, 8), (30, 7, 15)]):
        rng = np.random.default_rng(10 + k)
        H = _sparse_pd(rng, n, 1e-2, 0.15)
        g = rng.standard_normal(n)
        A = _sparse_rand(rng, n_eq, n, 0.15)
        C = _sparse_rand(rng, n_in, n, 0.15)
        xs = rng.standard_normal(n)
        up = C @ xs + rng.uniform(size=n_in)
        G, h = _two_sided(C, -1e20 * np.ones(n_in), up)
        out.append(QPProblem(f"strongly convex n={n} (l = -1e20)", "published", H, g, A, A @ xs, G, h, source=src))
        # Degenerate: every inequality row twice.
        Cd = np.vstack([C, C])
        out.append(QPProblem(f"degenerate n={n} (duplicated rows)", "degenerate", H, g, G=Cd,
                             h=Cd @ xs + rng.uniform(size=2 * n_in), source=src))
        # Not strongly convex: H PSD with a null space, g such that x_sol with random duals is optimal.
        Hs = _sparse_pd(rng, n, 0.0, 0.15)
        Hs -= np.linalg.eigvalsh(Hs).min() * np.eye(n)  # exactly singular (rank n − 1)
        ys, zs = rng.standard_normal(n_eq), rng.standard_normal(n_in)
        delta = rng.uniform(size=n_in)
        lo, hi = C @ xs - delta, C @ xs + delta
        gs = -(Hs @ xs + C.T @ zs + A.T @ ys)
        G2, h2 = _two_sided(C, lo, hi)
        out.append(QPProblem(f"not strongly convex n={n}", "singular P", Hs, gs, A, A @ xs, G2, h2, source=src))
        # Box constrained and unconstrained.
        out.append(QPProblem(f"box constrained n={n}", "published", H, g, lb=xs - 0.3, ub=xs + 0.3, source=src))
        out.append(QPProblem(f"unconstrained n={n}", "published", H, g, source=src))
    return out


# ------------------------------------------------------------------------------------------------
# Failure families: LPs, singular and degenerate problems, infeasible, unbounded, ill-scaled, ...
# ------------------------------------------------------------------------------------------------


def _lps() -> list[QPProblem]:
    rng = np.random.default_rng(5)
    C = rng.standard_normal((5, 10))
    w = rng.standard_normal(5)
    G, h = _two_sided(C, -np.ones(5), np.ones(5))
    Z2, Z3 = np.zeros((2, 2)), np.zeros((3, 3))
    out = [
        QPProblem("LP, unbounded optimal face (|Cx| ≤ 1, C 5×10)", "LP", np.zeros((10, 10)), C.T @ w, G=G, h=h),
        QPProblem("LP, degenerate vertex (3 active rows in 2-D)", "LP", Z2, np.array([-1.0, -1.0]),
                  G=np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0], [1.0, -1.0]]), h=np.array([1.0, 1.0, 2.0, 0.0])),
        QPProblem("LP, unbounded (min −x1, x ≥ 0, x2 ≤ 1)", "unbounded", Z2, np.array([-1.0, 0.0]),
                  G=np.array([[0.0, 1.0]]), h=np.ones(1), lb=np.zeros(2)),
        QPProblem("LP, infeasible (x1 + x2 ≤ −1, x ≥ 0)", "infeasible", Z2, np.ones(2), G=np.array([[1.0, 1.0]]),
                  h=-np.ones(1), lb=np.zeros(2)),
        QPProblem("LP, dependent equalities", "LP", Z3, np.array([1.0, 2.0, 3.0]),
                  A=np.array([[1.0, 1.0, 1.0], [1.0, 1.0, 1.0], [2.0, 2.0, 2.0]]), b=np.array([1.0, 1.0, 2.0]),
                  lb=np.zeros(3)),
        QPProblem("LP, Klee-Minty (n = 3)", "LP", Z3, -np.array([4.0, 2.0, 1.0]),
                  G=np.array([[1.0, 0, 0], [4.0, 1, 0], [8.0, 4, 1]]), h=np.array([5.0, 25.0, 125.0]), lb=np.zeros(3)),
        QPProblem("LP, n = 1, no constraint", "unbounded", np.zeros((1, 1)), np.ones(1)),
        QPProblem("LP, n = 1, x ≥ 0", "LP", np.zeros((1, 1)), np.ones(1), lb=np.zeros(1)),
        QPProblem("LP, zero objective (feasibility)", "LP", Z3, np.zeros(3), G=np.array([[1.0, 1.0, 1.0]]),
                  h=np.ones(1), lb=np.zeros(3)),
    ]
    # A random bounded LP with many rows (transportation-like simplex constraint).
    c = rng.uniform(1, 2, 8)
    out.append(QPProblem("LP, simplex (Σx = 1, x ≥ 0)", "LP", np.zeros((8, 8)), c, A=np.ones((1, 8)), b=np.ones(1),
                         lb=np.zeros(8)))
    return out


def _singular_unbounded_infeasible() -> list[QPProblem]:
    rng = np.random.default_rng(6)
    v = rng.standard_normal(4)
    Z2 = np.zeros((2, 2))
    return [
        QPProblem("P = 0, no constraint", "unbounded", Z2, np.array([1.0, 0.0])),
        QPProblem("P = vvᵀ, q ∉ range(P), no constraint", "unbounded", np.outer(v, v), np.array([1.0, 0.0, 0.0, 0.0])),
        QPProblem("P = vvᵀ, q ∈ range(P), no constraint", "singular P", np.outer(v, v), 2.0 * v),
        QPProblem("P singular, free direction bounded by a box", "singular P", np.diag([1.0, 0.0]), np.array([1.0, -1.0]),
                  lb=-np.ones(2), ub=np.ones(2)),
        QPProblem("P singular, unbounded along the null space", "unbounded", np.diag([1.0, 0.0]), np.array([1.0, -1.0]),
                  G=np.array([[1.0, 0.0]]), h=np.ones(1), lb=np.array([-1.0, -1.0])),
        QPProblem("QP, infeasible bounds lb > ub", "infeasible", np.eye(2), np.zeros(2), lb=np.array([1.0, 0.0]),
                  ub=np.array([0.0, 1.0])),
        QPProblem("QP, infeasible rows (x ≤ −1, x ≥ 1)", "infeasible", np.eye(2), np.zeros(2),
                  G=np.array([[1.0, 0.0], [-1.0, 0.0]]), h=np.array([-1.0, -1.0])),
        QPProblem("QP, inconsistent equalities", "infeasible", np.eye(3), np.zeros(3),
                  A=np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 0.0]]), b=np.array([1.0, 2.0])),
        QPProblem("QP, equalities against inequalities", "infeasible", np.eye(3), np.ones(3),
                  A=np.array([[1.0, 1.0, 1.0]]), b=np.array([3.0]), G=np.eye(3), h=0.5 * np.ones(3)),
        QPProblem("QP, p = n equalities (one point)", "equality-heavy", np.eye(3), np.ones(3),
                  A=np.array([[1.0, 0, 0], [1.0, 1, 0], [1.0, 1, 1]]), b=np.array([1.0, 2.0, 3.0]), G=np.eye(3),
                  h=5 * np.ones(3)),
        QPProblem("QP, p = n − 1 equalities and a box", "equality-heavy", np.diag([1.0, 2.0, 3.0, 4.0]), -np.ones(4),
                  A=rng.standard_normal((3, 4)), b=rng.standard_normal(3), lb=-3 * np.ones(4), ub=3 * np.ones(4)),
        QPProblem("QP, redundant active rows at the optimum", "degenerate", np.eye(2), np.array([-2.0, -2.0]),
                  G=np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0], [2.0, 2.0]]), h=np.array([1.0, 1.0, 2.0, 4.0])),
        QPProblem("unconstrained batch member P = I, q = 0", "published", np.eye(2), np.zeros(2)),
    ]


def _ill_scaled() -> list[QPProblem]:
    rng = np.random.default_rng(7)
    n, m = 6, 10
    M = rng.standard_normal((n, n))
    P = M @ M.T + 0.1 * np.eye(n)
    q = rng.standard_normal(n)
    G = rng.standard_normal((m, n))
    xf = rng.standard_normal(n)
    h = G @ xf + rng.uniform(size=m) * 0.1
    scale = np.logspace(-4, 4, m)
    d = np.logspace(-3, 3, n)
    Wl = rng.standard_normal((8, n)) @ np.diag(np.logspace(0, 3, n))
    return [
        QPProblem("large finite bound (ub = 1e10) beside x0 ≤ 1", "ill-scaled", 2 * np.eye(2), np.array([-4.0, 0.0]),
                  G=np.array([[1.0, 0.0]]), h=np.ones(1), ub=np.array([_INF, 1e10])),
        QPProblem("bounds ±1e20 mean none", "ill-scaled", 2 * np.eye(2), np.array([-4.0, 0.0]),
                  G=np.array([[1.0, 0.0]]), h=np.ones(1), lb=np.array([-1e20, -1e20]), ub=np.array([1e20, 1e20])),
        QPProblem("large finite bounds ±1e6", "ill-scaled", 2 * np.eye(2), np.array([-4.0, 0.0]),
                  G=np.array([[1.0, 0.0]]), h=np.ones(1), lb=np.array([-1e6, -1e6]), ub=np.array([1e6, 1e6])),
        QPProblem("rows scaled 1e-4 … 1e4", "ill-scaled", P, q, G=scale[:, None] * G, h=scale * h),
        QPProblem("P scaled 1e6, q 1e5", "ill-scaled", 1e6 * P, 1e5 * q, G=G, h=h),
        QPProblem("variables scaled 1e-3 … 1e3", "ill-scaled", d[:, None] * P * d[None, :], d * q, G=G * d[None, :], h=h),
        QPProblem("least squares, cond ~1e6, box", "ill-scaled", Wl.T @ Wl, -Wl.T @ rng.standard_normal(8),
                  lb=-np.ones(n), ub=np.ones(n), tags=("float32",)),
        QPProblem("infeasible, float32 too", "infeasible", np.eye(3), np.zeros(3), G=np.array([[1.0, 1.0, 1.0]]),
                  h=np.array([-1.0]), lb=np.zeros(3), tags=("float32",)),
        QPProblem("well-posed QP, float32 too", "published", P, q, G=G, h=h, tags=("float32",)),
    ]


def _defined() -> list[QPProblem]:
    """Problems whose status is a matter of definition: non-convex P, non-finite data, wrong-sign infinities."""
    I2, box = np.eye(2), (-np.ones(2), np.ones(2))
    G, h = np.array([[1.0, 1.0]]), np.array([1.0])
    nan = np.nan
    S = QPStatus
    return [
        QPProblem("non-convex P = −I, box", "non-convex", -I2, np.array([0.1, 0.0]), lb=box[0], ub=box[1], expect=S.NON_CONVEX),
        QPProblem("indefinite P = diag(1, −1), rows", "non-convex", np.diag([1.0, -1.0]), np.zeros(2), G=G, h=h,
                  lb=box[0], ub=box[1], expect=S.NON_CONVEX),
        QPProblem("lb = +inf", "wrong-sign infinity", I2, np.zeros(2), lb=np.array([_INF, 0.0]), expect=S.PRIMAL_INFEASIBLE),
        QPProblem("ub = −inf", "wrong-sign infinity", I2, np.zeros(2), ub=np.array([-_INF, 0.0]), expect=S.PRIMAL_INFEASIBLE),
        QPProblem("h = −inf", "wrong-sign infinity", I2, np.zeros(2), G=G, h=np.array([-_INF]), expect=S.PRIMAL_INFEASIBLE),
        QPProblem("lb = 1e20 (a lower bound at 'infinity')", "wrong-sign infinity", I2, np.zeros(2), lb=np.array([1e20, 0.0]),
                  expect=S.PRIMAL_INFEASIBLE),
        QPProblem("NaN in G", "invalid", I2, np.zeros(2), G=np.array([[nan, 1.0]]), h=h, expect=S.INVALID_INPUT),
        QPProblem("NaN in h", "invalid", I2, np.zeros(2), G=G, h=np.array([nan]), expect=S.INVALID_INPUT),
        QPProblem("inf in G", "invalid", I2, np.zeros(2), G=np.array([[_INF, 1.0]]), h=h, expect=S.INVALID_INPUT),
        QPProblem("NaN in lb", "invalid", I2, np.zeros(2), lb=np.array([nan, 0.0]), expect=S.INVALID_INPUT),
        QPProblem("NaN in ub", "invalid", I2, np.zeros(2), ub=np.array([nan, 0.0]), expect=S.INVALID_INPUT),
        QPProblem("NaN in P", "invalid", np.array([[nan, 0.0], [0.0, 1.0]]), np.zeros(2), G=G, h=h, expect=S.INVALID_INPUT),
        QPProblem("inf in P", "invalid", np.array([[_INF, 0.0], [0.0, 1.0]]), np.zeros(2), expect=S.INVALID_INPUT),
        QPProblem("NaN in q", "invalid", I2, np.array([nan, 0.0]), G=G, h=h, expect=S.INVALID_INPUT),
        QPProblem("inf in q", "invalid", I2, np.array([_INF, 0.0]), expect=S.INVALID_INPUT),
        QPProblem("NaN in A", "invalid", I2, np.zeros(2), A=np.array([[nan, 1.0]]), b=np.ones(1), expect=S.INVALID_INPUT),
        QPProblem("inf in b", "invalid", I2, np.zeros(2), A=np.array([[1.0, 1.0]]), b=np.array([_INF]), expect=S.INVALID_INPUT),
    ]


def peer_problems() -> list[QPProblem]:
    """Every problem of this module (published problems first), numpy float64."""
    return _qpsolvers() + _maros_meszaros() + _proxsuite() + _lps() + _singular_unbounded_infeasible() + _ill_scaled() + _defined()


RANDOM_FAMILIES = ("LP optimal face", "LP box+rows", "LP unbounded", "singular P", "degenerate", "equality-heavy",
                   "infeasible", "ill-scaled")
"""Families of `random_problem`: random members of the failure families, for sweeps on instances no test tuned."""


def random_problem(family: str, rng: np.random.Generator) -> QPProblem:
    """One random problem of `family` (2-13 variables; see RANDOM_FAMILIES)."""
    n = int(rng.integers(2, 14))
    if family == "LP optimal face":  # P = 0, |Cx| ≤ 1 with C k × n, k < n: the optimum is attained on an unbounded face
        k = int(rng.integers(1, n))
        C = rng.standard_normal((k, n))
        return QPProblem(family, family, np.zeros((n, n)), C.T @ rng.standard_normal(k), G=np.vstack([C, -C]), h=np.ones(2 * k))
    if family == "LP box+rows":
        m = int(rng.integers(1, 2 * n))
        G, x0 = rng.standard_normal((m, n)), rng.uniform(-0.5, 0.5, n)
        return QPProblem(family, family, np.zeros((n, n)), rng.standard_normal(n), G=G, h=G @ x0 + rng.uniform(0, 1, m),
                         lb=-np.ones(n), ub=np.ones(n))
    if family == "LP unbounded":  # every row keeps G d ≤ 0 along d, and the cost decreases along d
        m = int(rng.integers(1, n + 1))
        G, d = rng.standard_normal((m, n)), rng.standard_normal(n)
        G = G - np.outer((G @ d + np.abs(rng.standard_normal(m))) / (d @ d), d)
        return QPProblem(family, family, np.zeros((n, n)), -d, G=G, h=rng.uniform(0, 1, m))
    if family == "singular P":
        r, m = int(rng.integers(0, n)), int(rng.integers(1, 2 * n))
        M, G, x0 = rng.standard_normal((n, r)), rng.standard_normal((m, n)), rng.standard_normal(n)
        return QPProblem(family, family, M @ M.T, rng.standard_normal(n), G=G, h=G @ x0 + rng.uniform(0, 1, m), lb=x0 - 2, ub=x0 + 2)
    if family == "degenerate":  # many rows through one point, some repeated or scaled
        M = rng.standard_normal((n, n))
        P, q = M @ M.T + 0.1 * np.eye(n), rng.standard_normal(n)
        m = int(rng.integers(2, 2 * n))
        G = rng.standard_normal((m, n))
        h = G @ (-np.linalg.solve(P, q) + 0.3 * rng.standard_normal(n))
        G, h = np.vstack([G, G[: m // 2], 2 * G[: m // 3]]), np.concatenate([h, h[: m // 2], 2 * h[: m // 3]])
        return QPProblem(family, family, P, q, G=G, h=h)
    if family == "equality-heavy":  # p = n − 2 … n equalities, P definite, nearly singular or zero
        p, m = int(rng.integers(max(1, n - 2), n + 1)), int(rng.integers(1, n))
        M, x0, A, G = rng.standard_normal((n, n)), rng.standard_normal(n), rng.standard_normal((p, n)), rng.standard_normal((m, n))
        P = M @ M.T * float(rng.integers(0, 2)) + 1e-3 * float(rng.integers(0, 2)) * np.eye(n)
        return QPProblem(family, family, P, rng.standard_normal(n), A, A @ x0, G, G @ x0 + rng.uniform(0, 1, m), x0 - 3, x0 + 3)
    if family == "infeasible":  # g x ≤ −½ and −g x ≤ −½ among random rows; P definite or zero
        M, m = rng.standard_normal((n, n)), int(rng.integers(1, n))
        G, g = rng.standard_normal((m, n)), rng.standard_normal(n)
        G, h = np.vstack([G, g, -g]), np.concatenate([rng.uniform(0, 1, m), [-0.5, -0.5]])
        return QPProblem(family, family, M @ M.T * float(rng.integers(0, 2)), rng.standard_normal(n), G=G, h=h)
    if family == "ill-scaled":  # rows scaled 1e-4 … 1e4, variables 1e-2 … 1e2, P and q 1e-3 … 1e3
        M, m = rng.standard_normal((n, n)), int(rng.integers(1, 2 * n))
        P, G, x0 = M @ M.T + 1e-2 * np.eye(n), rng.standard_normal((m, n)), rng.standard_normal(n)
        h = G @ x0 + rng.uniform(0, 1, m)
        s, d = 10.0 ** rng.uniform(-4, 4, m), 10.0 ** rng.uniform(-2, 2, n)
        return QPProblem(family, family, 10.0 ** rng.uniform(-3, 3) * d[:, None] * P * d[None, :],
                         10.0 ** rng.uniform(-3, 3) * d * rng.standard_normal(n), G=s[:, None] * G * d[None, :], h=s * h)
    raise KeyError(f"unknown family {family!r}; one of {RANDOM_FAMILIES}")


def companion(p: QPProblem) -> QPProblem:
    """A strictly convex, feasible QP with p's sizes (x = 0 is feasible), for mixed batches."""
    n = p.n
    rows = {}
    if p.A is not None:
        rows["A"], rows["b"] = np.eye(n)[np.arange(p.A.shape[0]) % n], np.zeros(p.A.shape[0])
    if p.G is not None:
        rows["G"], rows["h"] = np.ones_like(p.G), np.ones(p.G.shape[0])
    if p.lb is not None:
        rows["lb"] = -np.ones(n)
    if p.ub is not None:
        rows["ub"] = np.ones(n)
    c = QPProblem(f"companion of {p.name}", "companion", np.eye(n) * 2.0, -np.linspace(0.5, 1.5, n), expect=None)
    return replace(c, **rows)


def reference(p: QPProblem, tol: float = 1e-10) -> tuple[QPStatus, np.ndarray | None, float | None]:
    """(status, x, optimal value) by cvxpy + Clarabel, or `p.expect` when it is set (x, value None)."""
    if p.expect is not None:
        return p.expect, None, None
    import cvxpy as cp

    n = p.n
    x = cp.Variable(n)
    cons = []
    if p.A is not None:
        cons.append(p.A @ x == p.b)
    if p.G is not None:
        keep = p.h < NO_BOUND
        if keep.any():
            cons.append(p.G[keep] @ x <= p.h[keep])
    if p.lb is not None:
        keep = p.lb > -NO_BOUND
        if keep.any():
            cons.append(x[np.flatnonzero(keep)] >= p.lb[keep])
    if p.ub is not None:
        keep = p.ub < NO_BOUND
        if keep.any():
            cons.append(x[np.flatnonzero(keep)] <= p.ub[keep])
    Ps = 0.5 * (p.P + p.P.T)
    obj = 0.5 * cp.quad_form(x, cp.psd_wrap(Ps)) + p.q @ x if np.any(Ps) else p.q @ x
    prob = cp.Problem(cp.Minimize(obj), cons)
    try:
        prob.solve(solver=cp.CLARABEL, tol_gap_abs=tol, tol_gap_rel=tol, tol_feas=tol, tol_ktratio=1e-8, max_iter=500)
    except cp.error.SolverError:  # very large finite data: Clarabel's defaults still converge
        prob.solve(solver=cp.CLARABEL, max_iter=500)
    status = {"optimal": QPStatus.SOLVED, "infeasible": QPStatus.PRIMAL_INFEASIBLE,
              "unbounded": QPStatus.DUAL_INFEASIBLE}.get(prob.status)
    if status is None:
        raise RuntimeError(f"Clarabel returned {prob.status!r} on {p.name!r}")
    if status != QPStatus.SOLVED:
        return status, None, None
    return status, np.asarray(x.value), float(objective(p, np.asarray(x.value)))
