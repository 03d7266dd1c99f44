/*
 * Dense Goldfarb-Idnani dual active set for small strictly convex QPs, one batch per call: the C route of
 * a3cqp_rl.qp.solve_qp (backend "c"), and the adjoint solve of its backward.
 *
 *     minimise ½ xᵀPx + qᵀx   subject to   A x = b (p rows),   G x ≤ h (m rows),   lb ≤ x ≤ ub,   P ≻ 0.
 *
 * Why C: at the controller's size (n ≈ 13, m ≈ 30) a whole solve is a few µs of arithmetic, which any
 * interpreted loop (numpy, eager torch) buries under per-call overhead; one call runs the whole batch.
 *
 * Input handling (the statuses of a3cqp_rl/qp/status.py, decided per instance): NaN anywhere, or ±inf in
 * P, q, A, b, G → INVALID_INPUT; a right-hand side or bound with |value| ≥ 1e20 of the "no constraint"
 * sign (h ≥ 1e20, lb ≤ −1e20, ub ≥ 1e20) is dropped, one of the other sign (h ≤ −1e20, lb ≥ 1e20,
 * ub ≤ −1e20) or lb > ub → PRIMAL_INFEASIBLE.  P is symmetrised, ½(P + Pᵀ).  The remaining rows are
 * assembled per instance (equalities first, then G rows, then −x ≤ −lb, then x ≤ ub).
 *
 * Method (Goldfarb & Idnani, "A numerically stable dual method for solving strictly convex
 * quadratic programs", Math. Programming 27, 1983), in the range space of P: with P = L Lᵀ,
 * x₀ = −P⁻¹q, the rows C, right-hand sides d and S = C P⁻¹ Cᵀ = MᵀM (M = L⁻¹Cᵀ), the KKT point of
 * a working set W has multipliers S_WW λ_W = C_W x₀ − d_W and row values
 * C x − d = (C x₀ − d) − S_{:W} λ_W.  From a dual-feasible start (λ_W ≥ 0) each step adds the most
 * violated row j (relative to its norm): first tried as a full step (the KKT point of W + j, taken
 * when its multipliers are ≥ 0, which is exactly when G-I takes the full step), otherwise by the
 * G-I partial steps that raise λ_j and drop a working row whose multiplier reaches zero first.
 * Every k × k system is solved by a fresh Cholesky factorisation (k ≤ n ≤ ~50: k³/6 flops, less
 * than the bookkeeping of an incremental update would save at this size).  Cold start: COLD_ROUNDS
 * rounds of "add the rows x₀ violates, trim to positive multipliers" (measured on 300 instances:
 * 1.07 / 6.60 / 12.07 solves at spread 0.015 / 0.35 / 1.0 with 2 rounds, 1.07 / 7.73 / 12.98 with 1).
 * Warm start: the working set {z0 > 0}, trimmed to positive multipliers; in the control loop that is
 * one k × k solve.  Where x₀ is large the range-space row values round coarsely (their decision threshold
 * counts that rounding) and can hide a small violation that the certificate's direct C x − d sees: after a
 * failed certificate that row is added by further G-I steps, up to POLISH_ROUNDS times.
 *
 * Nothing is returned as solved unless certified on the original KKT system, per row:
 *   stationarity  |(P x + q + Cᵀλ)_c| ≤ tol (1 + |q_c| + Σ_k |P_ck x_k| + Σ_a |C_ac λ_a|),
 *   every row     C_i x − d_i ≤ tol (1 + |d_i| + Σ_c |C_ic x_c|)   (|·| on the working rows),
 *   multipliers   λ_i ≥ −tol (1 + max |λ|) on the inequality rows,
 * so one large right-hand side loosens only its own row.  Nothing is returned as infeasible unless the Farkas
 * vector of G-I's infeasibility test passes the torch route's check (`farkas_certified`).  Any other outcome
 * (P not numerically positive definite, dependent working rows, an infeasible row without that certificate, the
 * step budget, a failed certificate) is an internal code ≥ 16 and the caller solves that instance on its torch
 * route, which has the singular-P, infeasibility and unboundedness machinery.
 *
 * Plain C99 + libm; row-major float64 arrays; one workspace per thread, kept between calls.  The same file is a
 * CPython extension module (`_gi_qp`: `solve` and `vjp`, the two entry points at the end, taking sizes, addresses as
 * ints or numpy arrays, and floats): the caller passes its output arrays as they are instead of taking their
 * addresses in Python (~0.3 µs each at B = 1, where a whole `solve_qp` is ~7 µs).
 * Compiled with -DGI_QP_NO_PYTHON it is plain C (the ctypes-callable gi_qp_solve / gi_qp_vjp only).
 */
#ifndef GI_QP_NO_PYTHON
#define PY_SSIZE_T_CLEAN
#include <Python.h> /* first, as Python requires */
#endif
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

/* Per-instance status: the QPStatus values decided here, then the codes that hand an instance on. */
enum {
    QP_SOLVED = 0,
    QP_PRIMAL_INFEASIBLE = 2,
    QP_INVALID_INPUT = 5,
    GI_NOT_DEFINITE = 16, /* P not numerically positive definite (Cholesky pivot ≤ 0) */
    GI_DEPENDENT = 17,    /* working rows (numerically) dependent: S_WW not definite */
    GI_INFEASIBLE = 18,   /* a violated row in the span of the working rows */
    GI_BUDGET = 19,       /* step budget spent */
    GI_UNCERTIFIED = 20,  /* final KKT / feasibility / dual-sign check failed */
    GI_NO_MEMORY = 21
};

/* Cold-start rounds of "add the violated rows, trim to positive multipliers". */
#define COLD_ROUNDS 2
/* A Cholesky pivot of S_WW below this fraction of its diagonal entry means dependent working rows
 * (rows at an angle below ~3e-7 rad). */
#define DEP_REL 1e-13
/* Relative rounding of a row value computed in the range space (a few hundred ulps of its terms). */
#define ROUND_REL 1e-13
/* Rounds of G-I steps after a failed certificate, each adding the row its direct evaluation shows violated. */
#define POLISH_ROUNDS 3
/* |bound| at and above which a bound or right-hand side means "none" (peers write 1e20 for it). */
#define NO_BOUND 1e20

typedef struct {
    int n, p, r;         /* variables, equalities, assembled rows of this instance (p first) */
    int m;               /* G rows of the input */
    const double *q;
    double *Ps;          /* n × n: ½(P + Pᵀ) */
    double *C, *d;       /* r × n assembled rows and their right-hand sides */
    int *rowmap;         /* assembled row -> output slot: y[0..p) | z[0..m) | z_lb[0..n) | z_ub[0..n) */
    double *thr;         /* per-row violation threshold of the active-set decisions (`thresholds`) */
    double tol;
    double *L, *Linv;    /* n × n Cholesky factor of P (lower), 1 / its diagonal */
    double *Ct;          /* the adjoint's working rows (k × n) */
    double *Mt;          /* n × r: M = L⁻¹Cᵀ */
    double *S;           /* r × r, rows (and the matching columns) filled on demand */
    unsigned char *have; /* have[i]: row i of S computed */
    unsigned char *W;    /* working-set membership */
    unsigned char *skip; /* rows found satisfied to within their certificate tolerance but dependent on the working set */
    int *buf;            /* working rows buf[0..k) (equalities first), buf[k] = row on trial */
    double *x0, *v0, *v, *ginv, *lw, *lwj, *dl, *rhs, *K, *Kinv, *x, *g, *t, *r1, *err_mag;
} gi_ws;

static const double *crow(const gi_ws *w, int i) { return w->C + (size_t)i * w->n; }

static double dot(const double *a, const double *b, int n) {
    double s = 0.0;
    for (int i = 0; i < n; ++i) s += a[i] * b[i];
    return s;
}

/* L y = b (L lower, row-major n × n, dinv = 1 / its diagonal: multiplications, not divisions,
 * on the dependency chain). */
static void fwd_sub(const double *L, const double *dinv, int n, const double *b, double *y) {
    for (int i = 0; i < n; ++i) y[i] = (b[i] - dot(L + (size_t)i * n, y, i)) * dinv[i];
}

/* Lᵀ y = b, column-oriented: once y_i is known it is eliminated from all earlier equations. */
static void bwd_sub_t(const double *L, const double *dinv, int n, const double *b, double *y) {
    if (y != b) memcpy(y, b, (size_t)n * sizeof(double));
    for (int i = n - 1; i >= 0; --i) {
        y[i] *= dinv[i];
        const double *Li = L + (size_t)i * n, yi = y[i];
        for (int k = 0; k < i; ++k) y[k] -= Li[k] * yi;
    }
}

/* In-place lower Cholesky of the k × k row-major K (1 / diagonal into dinv); pivots must exceed
 * rel × the original diagonal (rel = 0: only positivity, as LAPACK dpotrf).  0, or -1 if not definite. */
static int cholesky(double *K, double *dinv, int k, double rel) {
    for (int j = 0; j < k; ++j) {
        double *Kj = K + (size_t)j * k;
        double d = Kj[j] - dot(Kj, Kj, j);
        if (!(d > rel * Kj[j])) return -1; /* also catches NaN */
        double ljj = sqrt(d), inv = 1.0 / ljj;
        Kj[j] = ljj;
        dinv[j] = inv;
        for (int i = j + 1; i < k; ++i) {
            double *Ki = K + (size_t)i * k;
            Ki[j] = (Ki[j] - dot(Ki, Kj, j)) * inv;
        }
    }
    return 0;
}

/* y = Xᵀ u for X n × r row-major (y has r entries): axpy form, independent across y. */
static void mtv(const double *X, int n, int r, const double *u, double *y) {
    memset(y, 0, (size_t)r * sizeof(double));
    for (int k = 0; k < n; ++k) {
        const double *Xk = X + (size_t)k * r, uk = u[k];
        for (int c = 0; c < r; ++c) y[c] += uk * Xk[c];
    }
}

/* Row i of S = MᵀM (and its column, by symmetry), computed once. */
static void ensure_row(gi_ws *w, int i) {
    if (w->have[i]) return;
    const int r = w->r, n = w->n;
    double *Si = w->S + (size_t)i * r;
    memset(Si, 0, (size_t)r * sizeof(double));
    for (int k = 0; k < n; ++k) {
        const double *Mk = w->Mt + (size_t)k * r, a = Mk[i];
        for (int c = 0; c < r; ++c) Si[c] += a * Mk[c];
    }
    for (int c = 0; c < r; ++c) w->S[(size_t)c * r + i] = Si[c];
    w->have[i] = 1;
}

/* Whether all of a[0..len) are finite: on the bits, the exponent field plus one carries into the sign bit exactly
 * when it is all ones (±inf, NaN).  An OR reduction the compiler vectorises (a floating sum of x·0, the former test,
 * is a latency-bound chain: 11 % of a B = 1024 solve). */
static uint64_t exp_bits(double a) {
    uint64_t u;
    memcpy(&u, &a, sizeof u);
    return (u & 0x7ff0000000000000ULL) + 0x0010000000000000ULL; /* sign bit set iff a is ±inf or NaN */
}

static int finite_all(const double *a, int len) {
    uint64_t acc = 0;
    for (int i = 0; i < len; ++i) acc |= exp_bits(a[i]);
    return !(acc >> 63);
}

/* Solve S_RR y = rhs for the k rows R (their rows of S ensured); -1 if S_RR is not definite. */
static int solve_rows(gi_ws *w, const int *R, int k, const double *rhs, double *y) {
    const int r = w->r;
    for (int a = 0; a < k; ++a) {
        const double *Sa = w->S + (size_t)R[a] * r;
        for (int c = 0; c <= a; ++c) w->K[(size_t)a * k + c] = Sa[R[c]];
    }
    if (cholesky(w->K, w->Kinv, k, DEP_REL)) return -1;
    fwd_sub(w->K, w->Kinv, k, rhs, w->t);
    bwd_sub_t(w->K, w->Kinv, k, w->t, y);
    return 0;
}

/* Multipliers of the working set buf[0..k) (into lw): S_WW λ = v0_W. */
static int solve_working(gi_ws *w, int k, double *lw) {
    for (int a = 0; a < k; ++a) {
        ensure_row(w, w->buf[a]);
        w->rhs[a] = w->v0[w->buf[a]];
    }
    return solve_rows(w, w->buf, k, w->rhs, lw);
}

/* The point of working set buf[0..k) with multipliers lw: x = x₀ − P⁻¹ C_Wᵀ λ_W (into w->x; x₀ itself at k = 0). */
static const double *point_at(gi_ws *w, int k, const double *lw) {
    const int n = w->n;
    if (!k) return w->x0;
    memset(w->g, 0, (size_t)n * sizeof(double));
    for (int a = 0; a < k; ++a) {
        const double *Ca = w->C + (size_t)w->buf[a] * n;
        for (int c = 0; c < n; ++c) w->g[c] += lw[a] * Ca[c];
    }
    fwd_sub(w->L, w->Linv, n, w->g, w->t);
    bwd_sub_t(w->L, w->Linv, n, w->t, w->x);
    for (int c = 0; c < n; ++c) w->x[c] = w->x0[c] - w->x[c];
    return w->x;
}

/* Row values v = v0 − Σ λ_a S[buf_a, :] at the point of buf[0..k), and the decision thresholds there: row i
 * counts as violated when v_i exceeds tol (1 + |d_i| + Σ_c |C_ic x_c|), the certificate's own tolerance for it,
 * plus the rounding of v_i itself, ROUND_REL (|v0_i| + Σ_a |λ_a S_ai|) (where P is nearly singular, x₀ is large and
 * v_i a small difference of large terms), so that neither adds a (nearly dependent) row the certificate accepts. */
static void row_values(gi_ws *w, int k, const double *lw) {
    const int r = w->r, n = w->n;
    double *err = w->ginv + r; /* scratch: r entries after ginv */
    memcpy(w->v, w->v0, (size_t)r * sizeof(double));
    for (int i = 0; i < r; ++i) err[i] = fabs(w->v0[i]);
    for (int a = 0; a < k; ++a) {
        const double *Sa = w->S + (size_t)w->buf[a] * r, la = lw[a], al = fabs(la);
        for (int c = 0; c < r; ++c) w->v[c] -= la * Sa[c], err[c] += al * fabs(Sa[c]);
    }
    const double *x = point_at(w, k, lw);
    for (int i = 0; i < r; ++i) {
        const double *Ci = w->C + (size_t)i * n;
        double mag = 1.0 + fabs(w->d[i]);
        for (int c = 0; c < n; ++c) mag += fabs(Ci[c] * x[c]);
        w->thr[i] = w->tol * mag + ROUND_REL * err[i];
    }
}

/* min over the inequality multipliers lw[p..k) (+inf when there are none). */
static double min_ineq(const double *lw, int p, int k) {
    double mn = INFINITY;
    for (int a = p; a < k; ++a)
        if (!(lw[a] >= mn)) mn = lw[a];
    return mn;
}

/* 1 / ‖C_i‖ (+1e-300), computed when first asked for (only violated rows are ranked by it; ginv[i] < 0: not yet). */
static double row_ginv(gi_ws *w, int i) {
    double g = w->ginv[i];
    if (g < 0.0) g = w->ginv[i] = 1.0 / (sqrt(dot(crow(w, i), crow(w, i), w->n)) + 1e-300);
    return g;
}

/* Most violated inequality row relative to its norm, among the rows above their own threshold
 * (first on ties); -1 if none is violated. */
static int most_violated(gi_ws *w) {
    int j = -1;
    double best = -INFINITY;
    for (int i = w->p; i < w->r; ++i) {
        if (!(w->v[i] > w->thr[i]) || w->skip[i]) continue;
        double rel = w->v[i] * row_ginv(w, i);
        if (rel > best) best = rel, j = i;
    }
    return j;
}

/* Whether any of a[0..len) is NaN. */
static int any_nan(const double *a, int len) {
    for (int i = 0; i < len; ++i)
        if (a[i] != a[i]) return 1;
    return 0;
}

/* Checks one instance's data and assembles its rows into the workspace (see the header); returns 0,
 * QP_INVALID_INPUT or QP_PRIMAL_INFEASIBLE. */
static int assemble(gi_ws *w, const double *P, const double *q, const double *A, const double *b,
                    const double *G, const double *h, const double *lb, const double *ub, double tol) {
    const int n = w->n, p = w->p, m = w->m;
    /* P and G are tested for ±inf / NaN while they are read anyway (symmetrised, copied): one pass over each
     * instead of two; every INVALID_INPUT test still comes before any PRIMAL_INFEASIBLE answer. */
    uint64_t bad = 0;
    for (int i = 0; i < n; ++i)
        for (int j = 0; j < n; ++j) {
            const double a = P[(size_t)i * n + j];
            bad |= exp_bits(a);
            w->Ps[(size_t)i * n + j] = 0.5 * (a + P[(size_t)j * n + i]);
        }
    if (!finite_all(q, n) || !finite_all(A, p * n) || !finite_all(b, p) || any_nan(h, m) || (lb && any_nan(lb, n))
        || (ub && any_nan(ub, n)))
        return QP_INVALID_INPUT;
    w->q = q;
    int r = 0;
    for (int i = 0; i < p; ++i, ++r) {
        memcpy(w->C + (size_t)r * n, A + (size_t)i * n, (size_t)n * sizeof(double));
        w->d[r] = b[i], w->rowmap[r] = i;
    }
    int infeasible = 0;
    for (int i = 0; i < m; ++i) {
        const double *Gi = G + (size_t)i * n;
        if (h[i] >= NO_BOUND || h[i] <= -NO_BOUND) { /* no row, or an infeasible one: its entries still tested */
            for (int c = 0; c < n; ++c) bad |= exp_bits(Gi[c]);
            infeasible |= h[i] <= -NO_BOUND;
            continue;
        }
        double *Cr = w->C + (size_t)r * n;
        for (int c = 0; c < n; ++c) Cr[c] = Gi[c], bad |= exp_bits(Gi[c]);
        w->d[r] = h[i], w->rowmap[r++] = p + i;
    }
    if (bad >> 63) return QP_INVALID_INPUT;
    if (infeasible) return QP_PRIMAL_INFEASIBLE;
    for (int side = 0; side < 2; ++side) {
        const double *bd = side ? ub : lb;
        if (!bd) continue;
        const double sign = side ? 1.0 : -1.0;
        for (int j = 0; j < n; ++j) {
            const double v = bd[j] * sign; /* the row sign · x_j ≤ sign · bound */
            if (v >= NO_BOUND) continue;
            if (v <= -NO_BOUND) return QP_PRIMAL_INFEASIBLE;
            if (side && lb && lb[j] > ub[j]) return QP_PRIMAL_INFEASIBLE;
            double *Cr = w->C + (size_t)r * n;
            memset(Cr, 0, (size_t)n * sizeof(double));
            Cr[j] = sign;
            w->d[r] = v, w->rowmap[r++] = p + m + side * n + j;
        }
    }
    w->r = r;
    w->tol = tol;
    return 0;
}

/* The KKT conditions of working set buf[0..k) at (w->x, lw), per row (see the header); the residuals of the
 * working set's equations go to w->r1 (stationarity, n) and w->rhs (C_W x − d_W, k).  1 when all hold. */
static int kkt_holds(gi_ws *w, int k, const double *lw, double tol, int rows_at_x0) {
    const int n = w->n, p = w->p, r = w->r;
    int ok = 1;
    double lmax = 0.0;
    for (int a = 0; a < k; ++a) lmax = fmax(lmax, fabs(lw[a]));
    /* Stationarity, component by component, against the magnitude of its terms.  Accumulated for all components at
     * once (axpy form, vectorised; Ps is exactly symmetric, so column j is row j): component c sums its terms in the
     * order q_c, P_c0 x_0, ..., P_c,n-1 x_n-1, λ_0 C_0c, ... as a dot product per component would. */
    double *mag_s = w->g; /* scratch, n */
    for (int c = 0; c < n; ++c) w->r1[c] = w->q[c], mag_s[c] = 1.0 + fabs(w->q[c]);
    for (int j = 0; j < n; ++j) {
        const double *Pj = w->Ps + (size_t)j * n, xj = w->x[j];
        for (int c = 0; c < n; ++c) {
            const double t = Pj[c] * xj;
            w->r1[c] += t, mag_s[c] += fabs(t);
        }
    }
    for (int a = 0; a < k; ++a) {
        const double *Ca = crow(w, w->buf[a]), la = lw[a];
        for (int c = 0; c < n; ++c) {
            const double t = la * Ca[c];
            w->r1[c] += t, mag_s[c] += fabs(t);
        }
    }
    for (int c = 0; c < n; ++c) ok &= fabs(w->r1[c]) <= tol * mag_s[c];
    /* Row values: the working rows tight, every row feasible, each against its own terms (at x = x₀ they
     * were computed with the thresholds: v0 and err_mag). */
    for (int i = 0; i < r; ++i) {
        double s, mag;
        if (rows_at_x0) {
            s = w->v0[i], mag = w->err_mag[i];
        } else {
            const double *Ci = crow(w, i);
            s = -w->d[i], mag = 1.0 + fabs(w->d[i]);
            for (int c = 0; c < n; ++c) s += Ci[c] * w->x[c], mag += fabs(Ci[c] * w->x[c]);
            w->err_mag[i] = mag;
        }
        w->t[i] = s;
        ok &= s <= tol * mag && (i >= p || -s <= tol * mag);
    }
    for (int a = 0; a < k; ++a) {
        const int i = w->buf[a];
        w->rhs[a] = w->t[i];
        ok &= fabs(w->t[i]) <= tol * w->err_mag[i] && (a < p || lw[a] >= -tol * (1.0 + lmax));
    }
    return ok;
}

/* Certificate on the original KKT system and the outputs of working set buf[0..k): x = x₀ − P⁻¹ C_Wᵀ λ_W, and
 * the multipliers scattered into out (y | z | z_lb | z_ub, zero elsewhere).  Where P is ill-conditioned the
 * range-space x is a small difference of large terms; up to two steps of iterative refinement on the working
 * set's KKT system (same factors: S_WW dλ = r_W − C_W P⁻¹ r₁, dx = −P⁻¹(r₁ + C_Wᵀ dλ)) recover the digits
 * before the certificate is given up.  x0_rows: x is x₀ and v0 / err_mag hold its row values and terms. */
static int certify(gi_ws *w, int k, double *lw, double tol, double *x_out, double *out, int nout, int x0_rows) {
    const int n = w->n;
    memcpy(w->x, point_at(w, k, lw), (size_t)n * sizeof(double));
    for (int pass = 0;; ++pass) {
        if (kkt_holds(w, k, lw, tol, x0_rows && pass == 0)) break;
        if (pass == 2) return GI_UNCERTIFIED;
        /* u = P⁻¹ r₁ (into g); dλ from S_WW; dx = −u − P⁻¹ C_Wᵀ dλ */
        fwd_sub(w->L, w->Linv, n, w->r1, w->t);
        bwd_sub_t(w->L, w->Linv, n, w->t, w->g);
        for (int a = 0; a < k; ++a) w->rhs[a] -= dot(crow(w, w->buf[a]), w->g, n);
        if (k && solve_rows(w, w->buf, k, w->rhs, w->dl)) return GI_UNCERTIFIED;
        memcpy(w->r1, w->g, (size_t)n * sizeof(double)); /* u */
        memset(w->g, 0, (size_t)n * sizeof(double));
        for (int a = 0; a < k; ++a) {
            const double *Ca = crow(w, w->buf[a]);
            for (int c = 0; c < n; ++c) w->g[c] += w->dl[a] * Ca[c];
            lw[a] += w->dl[a];
        }
        fwd_sub(w->L, w->Linv, n, w->g, w->t);
        bwd_sub_t(w->L, w->Linv, n, w->t, w->g);
        for (int c = 0; c < n; ++c) w->x[c] -= w->r1[c] + w->g[c];
    }
    memcpy(x_out, w->x, (size_t)n * sizeof(double));
    memset(out, 0, (size_t)nout * sizeof(double));
    for (int a = 0; a < k; ++a) out[w->rowmap[w->buf[a]]] = lw[a];
    return QP_SOLVED;
}

/* Σ_c |C_jc x_c| at the point of working set buf[0..k) with multipliers lw: the size of row j's terms, which
 * scales its tolerance in the certificate. */
static double row_terms_at(gi_ws *w, int k, const double *lw, int j) {
    const double *x = point_at(w, k, lw), *Cj = crow(w, j);
    double mag = 0.0;
    for (int c = 0; c < w->n; ++c) mag += fabs(Cj[c] * x[c]);
    return mag;
}

/* The Farkas vector of G-I's infeasibility test, checked on the original rows: row j violated and a combination
 * Σ dl_a C_a of the working rows with dl_a ≤ 0 on the inequalities gives u (u_j = 1, u_a = −dl_a, ≥ 0 on the
 * inequalities) with ray = Cᵀu ≈ 0 and gap = dᵀu < 0.  Accepted with the torch route's test (interior_point.py):
 * max |ray| ≤ −1e-7 gap, so any feasible point would have |x|₁ ≥ 1e7; where rounding in dl (a nearly dependent
 * working set) leaves a larger ray, the instance is handed on instead. */
static int farkas_certified(const gi_ws *w, int j, int k) {
    const int n = w->n;
    const double *Cj = crow(w, j), *dl = w->dl;
    double gap = w->d[j], ray_max = 0.0;
    for (int a = 0; a < k; ++a) gap -= dl[a] * w->d[w->buf[a]];
    if (!(gap < 0.0)) return 0;
    for (int c = 0; c < n; ++c) {
        double r = Cj[c];
        for (int a = 0; a < k; ++a) r -= dl[a] * crow(w, w->buf[a])[c];
        if (fabs(r) > ray_max) ray_max = fabs(r);
    }
    return ray_max <= -1e-7 * gap;
}

/* One instance.  z0: warm-start multipliers (z | z_lb | z_ub; working set {z0 > 0}) or NULL. */
static int solve_one(gi_ws *w, const double *z0, double tol, int max_steps, double *x_out, double *out, int nout,
                     int64_t *solves_out) {
    const int n = w->n, p = w->p, r = w->r;
    *solves_out = 0;
    if (z0 && !finite_all(z0, w->m + 2 * n)) z0 = NULL;

    memcpy(w->L, w->Ps, (size_t)n * n * sizeof(double));
    if (cholesky(w->L, w->Linv, n, 0.0)) return GI_NOT_DEFINITE;
    /* x₀ = −P⁻¹q */
    for (int c = 0; c < n; ++c) w->g[c] = -w->q[c];
    fwd_sub(w->L, w->Linv, n, w->g, w->t);
    bwd_sub_t(w->L, w->Linv, n, w->t, w->x0);
    memset(w->have, 0, (size_t)r);
    memset(w->W, 0, (size_t)r);
    memset(w->skip, 0, (size_t)r);
    /* Row values at x₀ and the decision thresholds there (as row_values at k = 0), in one pass; the terms'
     * sizes stay in err_mag for the certificate of x₀ itself. */
    for (int i = 0; i < r; ++i) {
        const double *Ci = crow(w, i);
        double s = 0.0, mag = 1.0 + fabs(w->d[i]);
        for (int c = 0; c < n; ++c) {
            const double t = Ci[c] * w->x0[c];
            s += t, mag += fabs(t);
        }
        w->v0[i] = w->v[i] = s - w->d[i];
        w->err_mag[i] = mag;
        w->thr[i] = tol * mag + ROUND_REL * fabs(w->v0[i]);
    }
    int violated = 0;
    for (int i = p; i < r && !violated; ++i) violated = w->v0[i] > w->thr[i];
    int k = p;
    for (int i = 0; i < p; ++i) w->buf[i] = i, w->W[i] = 1;
    int nwarm = 0;
    if (z0)
        for (int i = p; i < r; ++i) nwarm += z0[w->rowmap[i] - p] > 0.0;
    if (p == 0 && nwarm == 0 && !violated) {
        /* The unconstrained minimiser is feasible (the easy cold case): certify it, skip S. */
        *solves_out = 1;
        return certify(w, 0, w->lw, tol, x_out, out, nout, 1);
    }
    /* Mt = L⁻¹ Cᵀ, forward substitution on all r right-hand sides at once: entry (a, c) is C_ca less the entries
     * above it in column c times row a of L, then times 1 / L_aa.  Four columns at a time are accumulated in
     * registers, read straight from C (no transposed copy, no store and reload of Mt's row per term: together 25 %
     * of the batch's time when Mt was built row by row in axpy form; the same operations in the same order). */
    for (int a = 0; a < n; ++a) {
        double *Ma = w->Mt + (size_t)a * r;
        const double *La = w->L + (size_t)a * n, *Ca = w->C + a, inv = w->Linv[a];
        int c = 0;
        for (; c + 4 <= r; c += 4) {
            double s0 = Ca[(size_t)c * n], s1 = Ca[(size_t)(c + 1) * n], s2 = Ca[(size_t)(c + 2) * n],
                   s3 = Ca[(size_t)(c + 3) * n];
            for (int b2 = 0; b2 < a; ++b2) {
                const double *Mb = w->Mt + (size_t)b2 * r + c, lab = La[b2];
                s0 -= lab * Mb[0], s1 -= lab * Mb[1], s2 -= lab * Mb[2], s3 -= lab * Mb[3];
            }
            Ma[c] = s0 * inv, Ma[c + 1] = s1 * inv, Ma[c + 2] = s2 * inv, Ma[c + 3] = s3 * inv;
        }
        for (; c < r; ++c) {
            double s0 = Ca[(size_t)c * n];
            for (int b2 = 0; b2 < a; ++b2) s0 -= La[b2] * w->Mt[(size_t)b2 * r + c];
            Ma[c] = s0 * inv;
        }
    }
    for (int i = p; i < r; ++i) w->ginv[i] = -1.0; /* row norms on demand (row_ginv) */

    int64_t solves = 0;
    double *lw = w->lw;
    int warm_done = 0;
    if (nwarm && p + nwarm <= n) {
        /* Warm start: the previous working set, less the rows whose multipliers come out ≤ 0
         * (re-solved until all are positive), so the start is dual feasible as G-I requires.
         * In the control loop the set is still optimal and this is the only solve. */
        for (int i = p; i < r; ++i)
            if (z0[w->rowmap[i] - p] > 0.0) w->buf[k++] = i, w->W[i] = 1;
        for (;;) {
            ++solves;
            if (solve_working(w, k, lw)) { /* dependent warm rows: start cold */
                for (int a = p; a < k; ++a) w->W[w->buf[a]] = 0;
                k = p;
                break;
            }
            if (k == p || min_ineq(lw, p, k) > 0.0) { warm_done = 1; break; }
            int kk = p;
            for (int a = p; a < k; ++a) {
                if (lw[a] > 0.0) w->buf[kk++] = w->buf[a];
                else w->W[w->buf[a]] = 0;
            }
            k = kk;
        }
        if (warm_done) {
            row_values(w, k, lw);
        }
    }
    if (!warm_done) {
        /* Cold start: add the rows the current point violates (the
         * most violated relative to their norms, up to n − k working rows), then trim the set to
         * positive multipliers, so the start is dual feasible; COLD_ROUNDS times from the new point. */
        row_values(w, 0, NULL);
        int have_lw = 0;
        for (int rnd = 0; rnd < COLD_ROUNDS; ++rnd) {
            if (rnd) {
                int any = 0;
                for (int i = p; i < r && !any; ++i) any = w->v[i] > w->thr[i];
                if (!any) break;
            }
            /* Candidates (violated relative to their norm, not working) into buf[k..); when more
             * than `room` = n − k of them, the `room` most violated first (selection sort: m is small). */
            int room = k < n ? n - k : 0, nadd = 0; /* p > n equalities: none (they are dependent) */
            for (int i = p; i < r; ++i)
                if (w->v[i] > w->thr[i] && !w->W[i]) w->buf[k + nadd++] = i;
            if (nadd > room) {
                for (int a = 0; a < room; ++a) {
                    int best = a;
                    for (int c = a + 1; c < nadd; ++c) {
                        int bi = w->buf[k + best], ci = w->buf[k + c];
                        if (w->v[ci] * row_ginv(w, ci) > w->v[bi] * row_ginv(w, bi)) best = c;
                    }
                    int tmp = w->buf[k + a];
                    w->buf[k + a] = w->buf[k + best];
                    w->buf[k + best] = tmp;
                }
                nadd = room;
            }
            if (nadd == 0 && rnd) break;
            for (int a = k; a < k + nadd; ++a) w->W[w->buf[a]] = 1;
            k += nadd;
            ++solves;
            have_lw = 0;
            while (k) {
                if (solve_working(w, k, lw)) {
                    if (k == p) return GI_DEPENDENT; /* dependent equalities */
                    for (int a = p; a < k; ++a) w->W[w->buf[a]] = 0;
                    k = p;
                    ++solves;
                    continue;
                }
                have_lw = 1;
                if (k == p || min_ineq(lw, p, k) > 0.0) break;
                int kk = p;
                for (int a = p; a < k; ++a) {
                    if (lw[a] > 0.0) w->buf[kk++] = w->buf[a];
                    else w->W[w->buf[a]] = 0;
                }
                k = kk;
                ++solves;
                have_lw = 0;
            }
            row_values(w, have_lw ? k : 0, lw);
        }
        if (solves < 1) solves = 1;
    }

    /* G-I steps. */
    int exact = 1; /* lw holds the exact multipliers of buf[0..k) (no incremental update since) */
    int steps = 0, forced = -1, rounds = 0;
gi_steps:
    while (r > p) {
        int j = forced >= 0 ? forced : most_violated(w);
        forced = -1;
        if (j < 0) break; /* every row within its threshold (NaN values fail the certificate) */
        double vj = w->v[j];
        if (++steps > max_steps) return GI_BUDGET;
        ensure_row(w, j);
        /* Optimistic full step: the G-I path ends at the KKT point of W + j exactly when no
         * multiplier crosses zero on the way, i.e. when its multipliers are ≥ 0.  (Skipped at
         * k = n: k + 1 rows in n variables are dependent.) */
        w->buf[k] = j;
        if (k < n) {
            ++solves;
            if (solve_working(w, k + 1, w->lwj) == 0 && min_ineq(w->lwj, p, k + 1) >= 0.0) {
                ++k;
                w->W[j] = 1;
                memcpy(lw, w->lwj, (size_t)k * sizeof(double));
                exact = 1;
                row_values(w, k, lw);
                continue;
            }
        }
        exact = 0;
        /* G-I steps for row j: raise λ_j, keeping the working rows tight (dλ_W = −S_WW⁻¹ S_Wj per
         * unit); a working inequality whose multiplier reaches zero first is dropped. */
        const double Sjj = w->S[(size_t)j * r + j];
        double lam_j = 0.0;
        for (;;) {
            double curv, t1 = INFINITY;
            int il = -1;
            if (k) {
                for (int a = 0; a < k; ++a) w->rhs[a] = w->S[(size_t)j * r + w->buf[a]];
                ++solves;
                if (solve_rows(w, w->buf, k, w->rhs, w->dl)) return GI_DEPENDENT;
                curv = Sjj - dot(w->rhs, w->dl, k);
                for (int a = p; a < k; ++a)
                    if (w->dl[a] > 0.0 && lw[a] / w->dl[a] < t1) t1 = lw[a] / w->dl[a], il = a;
                if (t1 < 0.0) t1 = 0.0;
            } else {
                curv = Sjj;
            }
            double t2 = curv > 1e-12 * Sjj ? vj / curv : INFINITY;
            if (t1 == INFINITY && t2 == INFINITY) {
                /* Row j is (numerically) a combination of the working rows.  Violated beyond the
                 * certificate's own tolerance for it, the instance is infeasible (the torch route then
                 * looks for the certificate); within it, it is a dependent row that rounding put just
                 * over the decision threshold: it is left out of the search (the certificate checks it). */
                if (vj <= tol * (1.0 + fabs(w->d[j]) + row_terms_at(w, k, lw, j))) {
                    w->skip[j] = 1;
                    break;
                }
                return farkas_certified(w, j, k) ? QP_PRIMAL_INFEASIBLE : GI_INFEASIBLE;
            }
            double t = t1 < t2 ? t1 : t2;
            for (int a = 0; a < k; ++a) lw[a] -= t * w->dl[a];
            lam_j += t;
            if (t2 <= t1) { /* row j is tight: it joins (it sits at buf[k] already) */
                w->W[j] = 1;
                lw[k++] = lam_j;
                break;
            }
            /* Drop the working row at il: the last working row takes its place, j moves down. */
            w->W[w->buf[il]] = 0;
            int last = k - 1;
            w->buf[il] = w->buf[last];
            w->buf[last] = j;
            lw[il] = lw[last];
            k = last;
            vj -= t * curv;
            if (++steps > max_steps) return GI_BUDGET;
        }
        row_values(w, k, lw);
    }
    if (!exact) { /* exact multipliers of the final working set (drops the incremental rounding) */
        ++solves;
        if (solve_working(w, k, lw)) return GI_DEPENDENT;
    }
    *solves_out = solves;
    const int st = certify(w, k, lw, tol, x_out, out, nout, 0);
    if (st == GI_UNCERTIFIED && rounds++ < POLISH_ROUNDS) {
        /* The range-space row values were too coarse to see a violated row (a large x₀: their rounding threshold
         * exceeded the violation) that the certificate's direct C x − d shows (w->t): that row goes on with the
         * G-I steps, from the refined multipliers, as the next row to add. */
        double best = 0.0;
        for (int i = p; i < r; ++i) {
            if (w->W[i] || !(w->t[i] > tol * w->err_mag[i])) continue;
            const double rel = w->t[i] * row_ginv(w, i);
            if (rel > best) best = rel, forced = i;
        }
        if (forced >= 0) {
            w->v[forced] = w->t[forced];
            w->skip[forced] = 0;
            exact = 1;
            goto gi_steps;
        }
    }
    return st;
}

/* Hint that the `len` doubles at a (len 0: a shared array, already in cache) will be read soon.  The batch's data
 * (P and G of 1024 instances: ~4.6 MB) does not fit in cache: without the hint each instance starts by waiting on
 * memory (its input checks showed as 12 % of the batch's time). */
static void prefetch(const double *a, int64_t len) {
#if defined(__GNUC__)
    for (int64_t i = 0; i < len; i += 8) __builtin_prefetch(a + i, 0, 3);
#else
    (void)a, (void)len;
#endif
}

/* One workspace per thread, kept between calls and grown when a call needs more: a malloc and free of
 * ~80 kB per call cost as much as a whole small solve (the heap top is trimmed and faulted in again). */
static __thread double *tls_mem = NULL;
static __thread size_t tls_bytes = 0;

/* The workspace of one instance (reused across the batch): one block carved into the arrays of gi_ws;
 * NULL if out of memory.  rmax: the most rows an instance can have.  The adjoint uses a subset. */
static double *ws_alloc(gi_ws *w, int64_t n, int64_t p, int64_t m, int64_t rmax) {
    const int64_t r = rmax;
    const size_t nd = (size_t)(3 * n * n + r * n + r + r + 2 * r * n + r * r + 5 * r + 4 * (r + 1) + (r + 1) * (r + 1)
                               + 4 * n + r + (r > n ? r : n) + 8);
    const size_t bytes = nd * sizeof(double) + (size_t)(3 * r + 8) + (size_t)(2 * r + 4) * sizeof(int);
    if (bytes > tls_bytes) {
        double *grown = (double *)realloc(tls_mem, bytes);
        if (!grown) return NULL;
        tls_mem = grown, tls_bytes = bytes;
    }
    double *mem = tls_mem;
    w->n = (int)n, w->p = (int)p, w->m = (int)m, w->r = (int)r;
    double *cur = mem;
    w->Ps = cur, cur += n * n;
    w->C = cur, cur += r * n;
    w->d = cur, cur += r;
    w->thr = cur, cur += r;
    w->L = cur, cur += n * n;
    w->Linv = cur, cur += n;
    w->Kinv = cur, cur += r + 1;
    w->Ct = cur, cur += r * n;
    w->Mt = cur, cur += r * n;
    w->S = cur, cur += r * r;
    w->x0 = cur, cur += n;
    w->v0 = cur, cur += r;
    w->v = cur, cur += r;
    w->ginv = cur, cur += 2 * r; /* (and r doubles of scratch after it: row_values) */
    w->rhs = cur, cur += r + 1;
    w->lw = cur, cur += r + 1;
    w->lwj = cur, cur += r + 1;
    w->dl = cur, cur += r + 1;
    w->K = cur, cur += (r + 1) * (r + 1);
    w->x = cur, cur += n;
    w->g = cur, cur += n;
    w->t = cur, cur += (r > n ? r : n) + 1;
    w->r1 = cur, cur += n;
    w->err_mag = cur, cur += r;
    w->buf = (int *)(mem + nd);
    w->rowmap = w->buf + r + 2;
    w->have = (unsigned char *)(w->rowmap + r + 2);
    w->W = w->have + r + 1;
    w->skip = w->W + r + 1;
    return mem;
}

/*
 * Batch entry point.  Row-major float64 arrays: P [B, n, n], q [B, n], A [B, p, n], b [B, p], G [B, m, n],
 * h [B, m], lb, ub [B, n] or NULL (no bounds), z0 [B, m + 2n] or NULL (warm-start multipliers z | z_lb | z_ub).
 * stride[9]: the distance in doubles between consecutive instances of P, q, A, b, G, h, lb, ub, z0 (0: one
 * array shared by the whole batch).  Output, one buffer: x [B, n] | duals [B, p + m + 2n] (y | z | z_lb | z_ub) |
 * status [B] (QP_* / GI_* codes above, as int64) | solves [B] (k × k factorisations, int64).  Returns the largest
 * status of the batch (so the caller knows without reading them whether any instance was handed on), or -1 if
 * the workspace could not be allocated (statuses then say GI_NO_MEMORY).
 */
int gi_qp_solve(int64_t B, int64_t n, int64_t p, int64_t m,
                const double *P, const double *q, const double *A, const double *b, const double *G, const double *h,
                const double *lb, const double *ub, const double *z0, const int64_t *stride, double tol,
                int64_t max_steps, double *out) {
    double *x = out, *duals = out + B * n;
    int64_t *status = (int64_t *)(out + B * (n + p + m + 2 * n)), *solves = status + B;
    gi_ws w;
    const int64_t nout = p + m + 2 * n;
    int worst = 0;
    double *mem = ws_alloc(&w, n, p, m, p + m + 2 * n);
    if (!mem) {
        for (int64_t i = 0; i < B; ++i) status[i] = GI_NO_MEMORY, solves[i] = 0;
        return -1;
    }
    for (int64_t i = 0; i < B; ++i) {
        double *xi = x + i * n, *oi = duals + i * nout;
        solves[i] = 0;
        if (i + 1 < B) { /* the next instance's large arrays (~4.5 kB at the controller's size) stream in meanwhile;
                          * q, h, b and the bounds too made no measurable difference */
            prefetch(P + (i + 1) * stride[0], stride[0]);
            prefetch(G + (i + 1) * stride[4], stride[4]);
            if (A) prefetch(A + (i + 1) * stride[2], stride[2]);
        }
        w.m = (int)m;
        int st = assemble(&w, P + i * stride[0], q + i * stride[1], A + i * stride[2], b + i * stride[3],
                          G + i * stride[4], h + i * stride[5], lb ? lb + i * stride[6] : NULL,
                          ub ? ub + i * stride[7] : NULL, tol);
        if (st == 0)
            st = solve_one(&w, z0 ? z0 + i * stride[8] : NULL, tol, (int)max_steps, xi, oi, (int)nout, solves + i);
        if (st != QP_SOLVED) {
            memset(xi, 0, (size_t)n * sizeof(double));
            memset(oi, 0, (size_t)nout * sizeof(double));
        }
        status[i] = st;
        if (st > worst) worst = st;
    }
    return worst;
}

/*
 * Backward: the vector-Jacobian product of the solution map, i.e. the gradients of Σ gx·x with respect to all
 * QP data (P, q, A, b, G, h, lb, ub), per instance, on the arguments of gi_qp_solve as they were passed and on its
 * output buffer (x | duals | status).  Implicit differentiation of the KKT conditions (as OptNet / qpth):
 * working rows are the equalities and the strictly complementary active rows, z_i > max(slack_i, 0), of G x ≤ h,
 * −x ≤ −lb and x ≤ ub.  The adjoint system [[P, C_Wᵀ], [C_W, 0]] (wx, wν) = (gx, 0) is solved in the range
 * space: S_WW wν = C_W P⁻¹gx, wx = P⁻¹(gx − C_Wᵀ wν), and accepted with the torch backward's test on its
 * residual, ‖e‖₂ ≤ 1e-12 (1 + |gx|∞)(1 + |wν|∞).  Gradients (P symmetrised as in the solve):
 *   gP = −½(x wxᵀ + wx xᵀ), gq = −wx, gA = −(y wxᵀ + wy xᵀ), gb = wy, gG_i = −(z_i wxᵀ + wz_i xᵀ) and gh_i = wz_i on
 *   the working G rows (zero elsewhere), g_lb_j = −wν and g_ub_j = wν on the working bound rows.
 * Instances whose status is not SOLVED get zero gradients (no gradient through a point that is not an answer).
 *
 * layout[25] (int64): [0..6) batch strides of P, A, G, h, lb, ub (0: shared); [6] stride of gx; [7..15) offsets in
 * `out` of gP, gq, gA, gb, gG, gh, g_lb, g_ub (−1: not wanted); [15..23) their batch strides (0: one array summed
 * over the batch, the gradient of an argument shared by the batch); [23] offset of the adjoint status [B] (int64:
 * 0 done, else GI_* — P not definite, dependent rows, residual too large — and that instance's gradients are left
 * to the caller: zero in per-instance outputs, nothing added to summed ones); [24] unused.
 * Returns the largest adjoint status.
 */
static void put(double *o, int acc, double v) { if (acc) *o += v; else *o = v; }

int gi_qp_vjp(int64_t B, int64_t n, int64_t p, int64_t m,
              const double *P, const double *A, const double *G, const double *h, const double *lb, const double *ub,
              const double *sol, const double *gx, const int64_t *layout, double *out) {
    const int64_t nout = p + m + 2 * n;
    const double *X = sol, *D = sol + B * n;
    const int64_t *st = (const int64_t *)(sol + B * (n + nout));
    const int64_t *in_s = layout, gx_s = layout[6], *off = layout + 7, *os = layout + 15;
    int64_t *adj = (int64_t *)(out + layout[23]);
    const int64_t sizes[8] = {n * n, n, p * n, p, m * n, m, n, n};
    gi_ws w;
    int worst = 0;
    if (!ws_alloc(&w, n, p, m, p + m + 2 * n)) {
        for (int64_t i = 0; i < B; ++i) adj[i] = GI_NO_MEMORY;
        return GI_NO_MEMORY;
    }
    /* Summed outputs start at zero; per-instance ones are written (zeros included) instance by instance. */
    for (int g = 0; g < 8; ++g)
        if (off[g] >= 0 && os[g] == 0) memset(out + off[g], 0, (size_t)sizes[g] * sizeof(double));
    const int ni = (int)n, pi = (int)p, mi = (int)m;
    for (int64_t i = 0; i < B; ++i) {
        double *o[8];
        int acc[8];
        for (int g = 0; g < 8; ++g) o[g] = off[g] >= 0 ? out + off[g] + i * os[g] : NULL, acc[g] = os[g] == 0;
        adj[i] = 0;
        /* Per-instance outputs of this instance start at zero (rows off the working set stay so). */
        for (int g = 0; g < 8; ++g)
            if (o[g] && !acc[g]) memset(o[g], 0, (size_t)sizes[g] * sizeof(double));
        if (st[i] != QP_SOLVED) continue;
        const double *Pi = P + i * in_s[0], *Ai = A ? A + i * in_s[1] : NULL, *Gi = G ? G + i * in_s[2] : NULL;
        const double *hi = h ? h + i * in_s[3] : NULL, *lbi = lb ? lb + i * in_s[4] : NULL;
        const double *ubi = ub ? ub + i * in_s[5] : NULL, *gxi = gx + i * gx_s;
        const double *xi = X + i * n, *yi = D + i * nout, *zi = yi + p, *zl = zi + m, *zu = zl + n;
        for (int a = 0; a < ni; ++a)
            for (int c = 0; c <= a; ++c)
                w.L[(size_t)a * ni + c] = 0.5 * (Pi[(size_t)a * ni + c] + Pi[(size_t)c * ni + a]);
        for (int a = 0; a < ni; ++a) /* upper triangle of Ps for the residual test */
            for (int c = a + 1; c < ni; ++c) w.L[(size_t)a * ni + c] = w.L[(size_t)c * ni + a];
        memcpy(w.Ps, w.L, (size_t)(n * n) * sizeof(double));
        if (cholesky(w.L, w.Linv, ni, 0.0)) { adj[i] = GI_NOT_DEFINITE; worst = GI_NOT_DEFINITE > worst ? GI_NOT_DEFINITE : worst; continue; }
        /* Working rows: code a < p equality a; p ≤ a < p + m row a − p of G; then −e_j (lb), +e_j (ub). */
        int k = 0;
        for (int a = 0; a < pi; ++a) w.buf[k++] = a;
        for (int a = 0; a < mi; ++a) {
            const double slack = hi[a] - dot(Gi + (size_t)a * ni, xi, ni);
            if (zi[a] > (slack > 0.0 ? slack : 0.0)) w.buf[k++] = pi + a;
        }
        if (lbi)
            for (int j = 0; j < ni; ++j) {
                const double slack = xi[j] - lbi[j];
                if (zl[j] > (slack > 0.0 ? slack : 0.0)) w.buf[k++] = pi + mi + j;
            }
        if (ubi)
            for (int j = 0; j < ni; ++j) {
                const double slack = ubi[j] - xi[j];
                if (zu[j] > (slack > 0.0 ? slack : 0.0)) w.buf[k++] = pi + mi + ni + j;
            }
        if (k > ni) { adj[i] = GI_DEPENDENT; worst = GI_DEPENDENT > worst ? GI_DEPENDENT : worst; continue; }
        for (int a = 0; a < k; ++a) {
            const int row = w.buf[a];
            double *ca = w.Ct + (size_t)a * ni;
            if (row < pi) memcpy(ca, Ai + (size_t)row * ni, (size_t)ni * sizeof(double));
            else if (row < pi + mi) memcpy(ca, Gi + (size_t)(row - pi) * ni, (size_t)ni * sizeof(double));
            else {
                const int j = (row - pi - mi) % ni;
                memset(ca, 0, (size_t)ni * sizeof(double));
                ca[j] = row < pi + mi + ni ? -1.0 : 1.0;
            }
        }
        /* u = P⁻¹gx; rows m_a = L⁻¹ c_a; S_WW = M Mᵀ; wν from S_WW wν = C_W u. */
        fwd_sub(w.L, w.Linv, ni, gxi, w.t);
        bwd_sub_t(w.L, w.Linv, ni, w.t, w.x0);
        for (int a = 0; a < k; ++a) fwd_sub(w.L, w.Linv, ni, w.Ct + (size_t)a * ni, w.Mt + (size_t)a * ni);
        for (int a = 0; a < k; ++a) {
            for (int c = 0; c <= a; ++c) w.K[(size_t)a * k + c] = dot(w.Mt + (size_t)a * ni, w.Mt + (size_t)c * ni, ni);
            w.rhs[a] = dot(w.Ct + (size_t)a * ni, w.x0, ni);
        }
        if (k) {
            if (cholesky(w.K, w.Kinv, k, DEP_REL)) { adj[i] = GI_DEPENDENT; worst = GI_DEPENDENT > worst ? GI_DEPENDENT : worst; continue; }
            fwd_sub(w.K, w.Kinv, k, w.rhs, w.t);
            bwd_sub_t(w.K, w.Kinv, k, w.t, w.lw);
        }
        /* wx = u − P⁻¹ C_Wᵀ wν */
        memset(w.g, 0, (size_t)ni * sizeof(double));
        for (int a = 0; a < k; ++a)
            for (int c = 0; c < ni; ++c) w.g[c] += w.lw[a] * w.Ct[(size_t)a * ni + c];
        fwd_sub(w.L, w.Linv, ni, w.g, w.t);
        bwd_sub_t(w.L, w.Linv, ni, w.t, w.x);
        for (int c = 0; c < ni; ++c) w.x[c] = w.x0[c] - w.x[c];
        /* Acceptance test of the torch backward on the full KKT residual. */
        double e2 = 0.0, gmax = 0.0, numax = 0.0;
        mtv(w.Ps, ni, ni, w.x, w.t);
        for (int c = 0; c < ni; ++c) {
            const double e = w.t[c] + w.g[c] - gxi[c];
            e2 += e * e;
            if (fabs(gxi[c]) > gmax) gmax = fabs(gxi[c]);
        }
        for (int a = 0; a < k; ++a) {
            const double e = dot(w.Ct + (size_t)a * ni, w.x, ni);
            e2 += e * e;
            if (fabs(w.lw[a]) > numax) numax = fabs(w.lw[a]);
        }
        if (!(sqrt(e2) <= 1e-12 * (1.0 + gmax) * (1.0 + numax))) {
            adj[i] = GI_UNCERTIFIED;
            worst = GI_UNCERTIFIED > worst ? GI_UNCERTIFIED : worst;
            continue;
        }
        const double *wx = w.x;
        if (o[0])
            for (int a = 0; a < ni; ++a)
                for (int c = 0; c < ni; ++c) put(o[0] + (size_t)a * ni + c, acc[0], -0.5 * (xi[a] * wx[c] + wx[a] * xi[c]));
        if (o[1])
            for (int c = 0; c < ni; ++c) put(o[1] + c, acc[1], -wx[c]);
        /* wy: wν on the equalities (the first p working rows). */
        if (o[2])
            for (int a = 0; a < pi; ++a)
                for (int c = 0; c < ni; ++c) put(o[2] + (size_t)a * ni + c, acc[2], -(yi[a] * wx[c] + w.lw[a] * xi[c]));
        if (o[3])
            for (int a = 0; a < pi; ++a) put(o[3] + a, acc[3], w.lw[a]);
        for (int a = pi; a < k; ++a) {
            const int row = w.buf[a];
            const double wn = w.lw[a];
            if (row < pi + mi) {
                const int r = row - pi;
                if (o[4]) {
                    double *gGr = o[4] + (size_t)r * ni;
                    const double zr = zi[r];
                    for (int c = 0; c < ni; ++c) put(gGr + c, acc[4], -(zr * wx[c] + wn * xi[c]));
                }
                if (o[5]) put(o[5] + r, acc[5], wn);
            } else if (row < pi + mi + ni) {
                if (o[6]) put(o[6] + (row - pi - mi), acc[6], -wn);
            } else if (o[7]) {
                put(o[7] + (row - pi - mi - ni), acc[7], wn);
            }
        }
    }
    return worst;
}

#ifndef GI_QP_NO_PYTHON
/* ------------------------------------------------------------------------------------------------------------------
 * CPython entry points: the arguments of gi_qp_solve / gi_qp_vjp as Python ints (addresses; 0 for NULL) and a float,
 * parsed without building tuples (METH_FASTCALL).  The GIL is released for batches where the solve outweighs it.
 */
/* Buffers lent by the arguments of one call (released after it). */
typedef struct {
    Py_buffer view[16];
    int count;
} lent_t;

static void release_all(lent_t *lent) {
    for (int i = 0; i < lent->count; ++i) PyBuffer_Release(&lent->view[i]);
    lent->count = 0;
}

/* An address argument: an int (0: NULL), None (NULL), or a C-contiguous buffer (a numpy array: its data, held until
 * release_all; passing the array itself spares the caller ~0.3 µs of taking its address in Python). */
static void *arg_ptr(PyObject *o, lent_t *lent) {
    if (PyLong_Check(o)) return PyLong_AsVoidPtr(o);
    if (o == Py_None) return NULL;
    Py_buffer *v = &lent->view[lent->count];
    if (PyObject_GetBuffer(o, v, PyBUF_C_CONTIGUOUS)) return NULL;
    lent->count++;
    return v->buf;
}

/* args[0..4): sizes into iv; args[4..4 + na): addresses into pv. */
static int parse_args(PyObject *const *args, Py_ssize_t nargs, Py_ssize_t want, int64_t *iv, void **pv, int na,
                      lent_t *lent, const char *name) {
    lent->count = 0;
    if (nargs != want) {
        PyErr_Format(PyExc_TypeError, "%s takes %zd arguments, got %zd", name, want, nargs);
        return -1;
    }
    for (int i = 0; i < 4; ++i) iv[i] = PyLong_AsLongLong(args[i]);
    for (int i = 0; i < na && !PyErr_Occurred(); ++i) pv[i] = arg_ptr(args[4 + i], lent);
    if (PyErr_Occurred()) {
        release_all(lent);
        return -1;
    }
    return 0;
}

/* The GIL is released for batches of 8 or more only: a small batch solves in a few µs, of which releasing and
 * re-taking the lock would be a visible share. Returns the saved state to restore, or NULL. */
static PyThreadState *release_gil(int64_t batch) {
    return batch >= 8 ? PyEval_SaveThread() : NULL;
}

/* solve(B, n, p, m, P, q, A, b, G, h, lb, ub, z0, strides, tol, max_steps, out) -> worst status (addresses as ints
 * or buffers) */
static PyObject *py_solve(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    int64_t iv[4];
    void *pv[10];
    lent_t lent;
    if (parse_args(args, nargs, 17, iv, pv, 10, &lent, "solve")) return NULL;
    const double tol = PyFloat_AsDouble(args[14]);
    const int64_t max_steps = PyLong_AsLongLong(args[15]);
    double *out = PyErr_Occurred() ? NULL : (double *)arg_ptr(args[16], &lent);
    if (PyErr_Occurred()) {
        release_all(&lent);
        return NULL;
    }
    const double **d = (const double **)pv;
    PyThreadState *ts = release_gil(iv[0]);
    const int worst = gi_qp_solve(iv[0], iv[1], iv[2], iv[3], d[0], d[1], d[2], d[3], d[4], d[5], d[6], d[7], d[8],
                                  (const int64_t *)pv[9], tol, max_steps, out);
    if (ts) PyEval_RestoreThread(ts);
    release_all(&lent);
    return PyLong_FromLong(worst);
}

/* vjp(B, n, p, m, P, A, G, h, lb, ub, sol, gx, layout, out) -> worst adjoint status (addresses as ints or buffers) */
static PyObject *py_vjp(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    int64_t iv[4];
    void *pv[10];
    lent_t lent;
    if (parse_args(args, nargs, 14, iv, pv, 10, &lent, "vjp")) return NULL;
    const double **d = (const double **)pv;
    PyThreadState *ts = release_gil(iv[0]);
    const int worst = gi_qp_vjp(iv[0], iv[1], iv[2], iv[3], d[0], d[1], d[2], d[3], d[4], d[5], d[6], d[7],
                                (const int64_t *)pv[8], (double *)pv[9]);
    if (ts) PyEval_RestoreThread(ts);
    release_all(&lent);
    return PyLong_FromLong(worst);
}

static PyMethodDef gi_qp_methods[] = {
    {"solve", (PyCFunction)(void (*)(void))py_solve, METH_FASTCALL,
     "solve(B, n, p, m, P, q, A, b, G, h, lb, ub, z0, strides, tol, max_steps, out) -> worst status (gi_qp_solve)"},
    {"vjp", (PyCFunction)(void (*)(void))py_vjp, METH_FASTCALL,
     "vjp(B, n, p, m, P, A, G, h, lb, ub, sol, gx, layout, out) -> worst adjoint status (gi_qp_vjp)"},
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef gi_qp_module = {PyModuleDef_HEAD_INIT, "_gi_qp",
                                          "Dense Goldfarb-Idnani QP batches and their vector-Jacobian products (C).",
                                          -1, gi_qp_methods, NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__gi_qp(void) { return PyModule_Create(&gi_qp_module); }
#endif
