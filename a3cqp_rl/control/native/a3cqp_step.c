/*
 * The A3CQP controller's default step in C, one arm after the other: the QP assembly (context, the
 * four tasks and the Cartesian regularizer, the four limits) and, after the QP, the torque law.
 *
 * This is a translation of the Python objects, not a second design: each function below is one
 * object of a3cqp_rl/control (named in its comment) and computes the same numbers in the same
 * order, so that the two agree to rounding (tests/test_control_native.py checks 1e-9 on random,
 * contact and near-limit states).  The Python code is the reference and the only path for custom
 * tasks, limits, other devices and autograd; the controller takes this one for its default
 * composition on CPU float64 (see native/__init__.py for when and why: at B = 1 a step is a few
 * hundred numpy calls of 0.5-3 µs each while its arithmetic is ~20 k flops).
 *
 * Arrays are row-major float64.  The inputs of an arm are one packed row (the IN_* offsets below):
 * q, qd [7]; M = B(q) [7 7]; bias = h + g [7]; J [6 7] (linear rows first, world frame);
 * jdqd = J̇q̇ [6]; twist = J q̇ [6]; pos [3]; rot [3 3]; w = local task weights [6 3] (columns IK,
 * AC, FC); f_d [6]; pos_d [3]; rot_d [3 3]; f_ext [6]; contact [1] (0 or 1); q_des, qd_des [7]
 * (q*, q̇* of eq. 6-7).  Outputs are whole arrays one after the other, batch first.
 *
 * Plain C99 + libm, no allocation.
 */
#include <math.h>
#include <stddef.h>
#include <stdint.h>
#include <string.h>

#define NQ 7  /* q̈ = x[0:7] */
#define NW 6  /* f = x[7:13] */
#define NV 13

/* Parameters: each task and limit of a3cqp_rl/control hands its own fields (their `c_params`), the controller its
 * step-level ones; Python builds its ctypes view from the field table below, so the layout is declared once, here.
 * S(name): a scalar; A(name, n): an array of n.  Flags are doubles (0 or 1). */
#define A3CQP_PARAMS(S, A)                                                                                         \
    S(dt) S(cv) S(cp)                        /* control period [s]; eq. 5 gains c_v, c_p */                        \
    A(kp, 6) A(kv, 6)                        /* CartesianIK: K_p, K_v diagonals (eq. 10-11) */                     \
    S(lambda_d) S(c_d) S(ac_paper)           /* Admittance: Λd, Cd, eq. 18 as printed (1) or consistent (0) */     \
    S(f_d_max)                               /* FC: f_d clipped to [0, f̄_d] (eq. 21) */                            \
    S(wrench_ff) S(pd_pinv)                  /* ControllerOptions.ik_wrench_feedforward, pd_projection == "pinv" */\
    S(creg_gamma)                            /* CartesianAccelerationRegularizer γ (0: absent) */                  \
    A(q_center, 7) S(kq) S(jc_eps) S(jc_eps_n) /* JointCentering q_d, k_q, ε, ε_N (eq. 23) */                      \
    S(reg) S(pinv_damping) S(nullspace_damping)                                                                    \
    A(q_min, 7) A(q_max, 7) A(dq_max, 7) A(ddq_max, 7) /* JointLimitsViability (margins applied) */                \
    S(horizon) S(target_total) S(include_f_ext) S(brake_gain)                                                      \
    S(has_tau_stop) A(tau_stop_max, 7) S(torque_share) S(min_stop_fraction) S(stop_share)                          \
    A(wrench_max, 6)                         /* WrenchBox */                                                       \
    S(mu)                                    /* FrictionPyramid */                                                 \
    S(has_torque_limits) A(torque_max, 7) S(torque_safe) /* TorqueLimits (scaled τ̄), anchored to the brake */      \
    A(tau_clip, 7) S(leak) S(leak_per_axis)  /* torque clip ±τ_max; Δt · desired_state_leak; leak_axes */   \
    S(wrench_sum)                            /* ControllerOptions.wrench_blend == "weighted_sum" */

#define DECLARE_S(f) double f;
#define DECLARE_A(f, n) double f[n];
typedef struct { A3CQP_PARAMS(DECLARE_S, DECLARE_A) } a3cqp_params;

/* (name, offset in doubles, count) of each parameter and of each entry of the per-arm input row, for the bindings. */
typedef struct { const char *name; int64_t offset, count; } a3cqp_field;
#define FIELD_S(f) {#f, (int64_t)(offsetof(a3cqp_params, f) / sizeof(double)), 1},
#define FIELD_A(f, n) {#f, (int64_t)(offsetof(a3cqp_params, f) / sizeof(double)), n},
static const a3cqp_field PARAM_FIELDS[] = { A3CQP_PARAMS(FIELD_S, FIELD_A) };

int64_t a3cqp_param_fields(const a3cqp_field **out) {
    *out = PARAM_FIELDS;
    return (int64_t)(sizeof(PARAM_FIELDS) / sizeof(PARAM_FIELDS[0]));
}

int64_t a3cqp_params_size(void) { return (int64_t)sizeof(a3cqp_params); }

/* Per-robot fields of a population (PopulationController: each arm its own gains and, per strict level, which
 * tasks count in that level's cost): a3cqp_assemble_robots reads one row of these per arm; they replace the
 * parameter of the same name (kp .. creg_gamma) or scale a task's cost (cost_ik: IK's W1 in the q̈ block and, with
 * wrench_sum, in the f block; cost_ac: W2; cost_fc: W3; JC and the regularizer are scaled through their own
 * jc_eps, jc_eps_n, creg_gamma). The weights w stay whole: eq. 5's P W1 J and the wrench feed-forward use them. */
#define A3CQP_ROBOT(S, A)                                                                                          \
    A(kp, 6) A(kv, 6) S(lambda_d) S(c_d) S(kq) S(jc_eps) S(jc_eps_n) S(creg_gamma) S(cost_ik) S(cost_ac) S(cost_fc)
typedef struct { A3CQP_ROBOT(DECLARE_S, DECLARE_A) } a3cqp_robot;
#define RFIELD_S(f) {#f, (int64_t)(offsetof(a3cqp_robot, f) / sizeof(double)), 1},
#define RFIELD_A(f, n) {#f, (int64_t)(offsetof(a3cqp_robot, f) / sizeof(double)), n},
static const a3cqp_field ROBOT_FIELDS[] = { A3CQP_ROBOT(RFIELD_S, RFIELD_A) };

int64_t a3cqp_robot_fields(const a3cqp_field **out) {
    *out = ROBOT_FIELDS;
    return (int64_t)(sizeof(ROBOT_FIELDS) / sizeof(ROBOT_FIELDS[0]));
}

int64_t a3cqp_robot_size(void) { return (int64_t)(sizeof(a3cqp_robot) / sizeof(double)); }

/* Rows of the inequality block: joint limits (2 or 4 sets of 7), wrench box 12, friction 4, torque 14. */
int64_t a3cqp_rows(const a3cqp_params *p) {
    return (p->target_total != 0.0 ? 28 : 14) + 12 + 4 + (p->has_torque_limits != 0.0 ? 14 : 0);
}

/* ------------------------------------------------------------------ small dense helpers */

/* X = A⁻¹ B by Gauss-Jordan with partial pivoting (A n × n, B n × r; B = NULL: the inverse). Returns 0 if a pivot
 * is exactly zero (X is then NaN, as numpy's singular solve would leave the controller: the step falls back). */
static int gj_solve(int n, const double *A, int r, const double *B, double *X) {
    double a[7 * 7], b[7 * 7];
    memcpy(a, A, sizeof(double) * n * n);
    if (B) memcpy(b, B, sizeof(double) * n * r);
    else {
        r = n;
        memset(b, 0, sizeof(double) * n * n);
        for (int i = 0; i < n; i++) b[i * n + i] = 1.0;
    }
    for (int k = 0; k < n; k++) {
        int piv = k;
        for (int i = k + 1; i < n; i++)
            if (fabs(a[i * n + k]) > fabs(a[piv * n + k])) piv = i;
        if (a[piv * n + k] == 0.0) {
            for (int i = 0; i < n * r; i++) X[i] = NAN;
            return 0;
        }
        if (piv != k) {
            for (int j = 0; j < n; j++) { double t = a[k * n + j]; a[k * n + j] = a[piv * n + j]; a[piv * n + j] = t; }
            for (int j = 0; j < r; j++) { double t = b[k * r + j]; b[k * r + j] = b[piv * r + j]; b[piv * r + j] = t; }
        }
        double inv = 1.0 / a[k * n + k];
        for (int j = 0; j < n; j++) a[k * n + j] *= inv;
        for (int j = 0; j < r; j++) b[k * r + j] *= inv;
        for (int i = 0; i < n; i++) {
            double f = a[i * n + k];
            if (i == k || f == 0.0) continue;
            for (int j = 0; j < n; j++) a[i * n + j] -= f * a[k * n + j];
            for (int j = 0; j < r; j++) b[i * r + j] -= f * b[k * r + j];
        }
    }
    memcpy(X, b, sizeof(double) * n * r);
    return 1;
}

/* C = A B (A m × k, B k × n). */
static void mm(int m, int k, int n, const double *A, const double *B, double *C) {
    for (int i = 0; i < m; i++) {
        double *c = C + i * n;
        for (int j = 0; j < n; j++) c[j] = 0.0;
        for (int l = 0; l < k; l++) {
            double a = A[i * k + l];
            const double *b = B + l * n;
            for (int j = 0; j < n; j++) c[j] += a * b[j];
        }
    }
}

/* C = Aᵀ B (A stored k × m, B k × n). */
static void mm_tn(int m, int k, int n, const double *A, const double *B, double *C) {
    for (int i = 0; i < m * n; i++) C[i] = 0.0;
    for (int l = 0; l < k; l++)
        for (int i = 0; i < m; i++) {
            double a = A[l * m + i];
            const double *b = B + l * n;
            double *c = C + i * n;
            for (int j = 0; j < n; j++) c[j] += a * b[j];
        }
}

/* C = A Bᵀ (A m × k, B stored n × k). */
static void mm_nt(int m, int k, int n, const double *A, const double *B, double *C) {
    for (int i = 0; i < m; i++)
        for (int j = 0; j < n; j++) {
            double s = 0.0;
            for (int l = 0; l < k; l++) s += A[i * k + l] * B[j * k + l];
            C[i * n + j] = s;
        }
}

/* y = A x (A m × k). */
static void mv(int m, int k, const double *A, const double *x, double *y) {
    for (int i = 0; i < m; i++) {
        double s = 0.0;
        for (int l = 0; l < k; l++) s += A[i * k + l] * x[l];
        y[i] = s;
    }
}

/* y = Aᵀ x (A stored k × m). */
static void mtv(int m, int k, const double *A, const double *x, double *y) {
    for (int i = 0; i < m; i++) y[i] = 0.0;
    for (int l = 0; l < k; l++)
        for (int i = 0; i < m; i++) y[i] += A[l * m + i] * x[l];
}

static double clampd(double v, double lo, double hi) { return v < lo ? lo : (v > hi ? hi : v); }

/* ------------------------------------------------------------------ context (ControlContext, build_context) */

typedef struct {
    double binv_jt[7 * 6];   /* B⁻¹Jᵀ */
    double lam_inv[36], lam[36]; /* Λ⁻¹ = J B⁻¹ Jᵀ + λ² I, Λ (eq. 12) */
    double D[36];            /* blockdiag(R, R) (eq. 3) */
    double W[3][36];         /* W1, W2, W3 = D diag(w_i) Dᵀ (eq. 8) */
    double jpinv[7 * 6];     /* J⁺ = Jᵀ (J Jᵀ + λ² I)⁻¹ */
    double w1j[6 * 7];       /* W1 J */
    double pd[49];           /* P W1 J (eq. 5) */
    double qdd_map[49];      /* I + (c_v Δt + c_p Δt²/2) P W1 J */
    double qdd_pd0[7];       /* q̈_pd at q̈* = 0 */
    double nullspace[49];    /* I − J⁺J */
    double jtw1j[49];        /* Jᵀ W1 J */
    double pose_err[6];      /* e_x (eq. 10) */
    double fdl[6];           /* f_d^𝓛 clipped (eq. 21) */
} context;

/* frames.rotation_log of R_d Rᵀ: the rotation vector θ·axis (exact for θ < π). */
static void rotation_error(const double *rot_d, const double *rot, double *e) {
    double E[9];
    mm_nt(3, 3, 3, rot_d, rot, E);
    double v[3] = {0.5 * (E[7] - E[5]), 0.5 * (E[2] - E[6]), 0.5 * (E[3] - E[1])}; /* sin θ · axis */
    double s = sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
    double c = 0.5 * (E[0] + E[4] + E[8] - 1.0);
    double theta = atan2(s, c);
    double scale = s > 1e-9 ? theta / (s > 1e-12 ? s : 1e-12) : 1.0 + theta * theta / 6.0;
    for (int i = 0; i < 3; i++) e[i] = scale * v[i];
}

static void build_context(const a3cqp_params *p, const double *q, const double *qd, const double *M, const double *J,
                          const double *pos, const double *rot, const double *w, const double *f_d, const double *pos_d,
                          const double *rot_d, const double *q_des, const double *qd_des, context *c) {
    double Jt[7 * 6];
    for (int i = 0; i < 6; i++)
        for (int j = 0; j < 7; j++) Jt[j * 6 + i] = J[i * 7 + j];
    gj_solve(7, M, 6, Jt, c->binv_jt);
    mm(6, 7, 6, J, c->binv_jt, c->lam_inv);
    for (int i = 0; i < 6; i++) c->lam_inv[i * 6 + i] += p->pinv_damping;
    double lam[36];
    gj_solve(6, c->lam_inv, 0, NULL, lam);
    for (int i = 0; i < 6; i++)
        for (int j = 0; j < 6; j++) c->lam[i * 6 + j] = 0.5 * (lam[i * 6 + j] + lam[j * 6 + i]);
    memset(c->D, 0, sizeof c->D);
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) c->D[i * 6 + j] = c->D[(i + 3) * 6 + j + 3] = rot[i * 3 + j];
    for (int k = 0; k < 3; k++) {
        double Dw[36];
        for (int i = 0; i < 6; i++)
            for (int a = 0; a < 6; a++) Dw[i * 6 + a] = c->D[i * 6 + a] * w[a * 3 + k];
        mm_nt(6, 6, 6, Dw, c->D, c->W[k]);
    }
    double jjt[36], jjt_inv[36];
    mm_nt(6, 7, 6, J, J, jjt);
    for (int i = 0; i < 6; i++) jjt[i * 6 + i] += p->nullspace_damping;
    gj_solve(6, jjt, 0, NULL, jjt_inv);
    mm_tn(7, 6, 6, J, jjt_inv, c->jpinv);
    mm(6, 6, 7, c->W[0], J, c->w1j);
    if (p->pd_pinv != 0.0) mm(7, 6, 7, c->jpinv, c->w1j, c->pd);
    else mm_tn(7, 6, 7, J, c->w1j, c->pd);
    double err[7];
    for (int i = 0; i < 7; i++)
        err[i] = p->cv * (qd_des[i] - qd[i]) + p->cp * (q_des[i] + p->dt * qd_des[i] - q[i]);
    double gain = p->cv * p->dt + p->cp * p->dt * p->dt / 2.0;
    mv(7, 7, c->pd, err, c->qdd_pd0);
    double jpj[49];
    mm(7, 6, 7, c->jpinv, J, jpj);
    for (int i = 0; i < 49; i++) {
        double eye = (i % 8 == 0) ? 1.0 : 0.0;
        c->qdd_map[i] = eye + gain * c->pd[i];
        c->nullspace[i] = eye - jpj[i];
    }
    mm_tn(7, 6, 7, J, c->w1j, c->jtw1j);
    for (int i = 0; i < 3; i++) c->pose_err[i] = pos_d[i] - pos[i];
    rotation_error(rot_d, rot, c->pose_err + 3);
    for (int i = 0; i < 6; i++) c->fdl[i] = clampd(f_d[i], 0.0, p->f_d_max);
}

/* ------------------------------------------------------------------ limits (limits.py) */

/* _acc_bounds_from_position, _from_viability and _acc_bounds for one joint (Del Prete 2017). */
static void joint_bounds(double q, double dq, double q_min, double q_max, double dq_max, double ddq_max,
                         double ddq_stop, double dt, double *lb_out, double *ub_out) {
    /* position */
    double two_dt_sq = 2.0 / (dt * dt);
    double ub_q3 = two_dt_sq * (q_max - q - dt * dq), lb_q3 = two_dt_sq * (q_min - q - dt * dq);
    double stop = -dq / dt, dq2 = dq * dq;
    double lb_brake = fmax(dq2 / (2.0 * (q != q_min ? q - q_min : 1.0)), stop);
    double lb_down = lb_q3 < stop ? lb_q3 : (q != q_min ? lb_brake : stop);
    double ub_brake = fmin(-dq2 / (2.0 * (q != q_max ? q_max - q : 1.0)), stop);
    double ub_up = ub_q3 > stop ? ub_q3 : (q != q_max ? ub_brake : stop);
    int down = dq <= 0.0;
    double lb_p = down ? lb_down : lb_q3, ub_p = down ? ub_q3 : ub_up;
    /* velocity */
    double lb_v = (-dq_max - dq) / dt, ub_v = (dq_max - dq) / dt;
    /* viability */
    double dt2 = dt * dt, two_a = 2.0 * dt2;
    double b = 2.0 * dt * dq + ddq_stop * dt2;
    double cc = dq2 - 2.0 * ddq_stop * (q_max - q - dt * dq);
    double delta = b * b - 2.0 * two_a * cc;
    double ub_s = delta >= 0.0 ? (-b + sqrt(fmax(delta, 0.0))) / two_a : stop;
    b = 2.0 * dt * dq - ddq_stop * dt2;
    cc = dq2 - 2.0 * ddq_stop * (q + dt * dq - q_min);
    delta = b * b - 2.0 * two_a * cc;
    double lb_s = delta >= 0.0 ? (-b - sqrt(fmax(delta, 0.0))) / two_a : stop;
    lb_s = fmin(lb_s, stop);
    ub_s = fmax(ub_s, stop);
    /* combine; on conflict drop viability, then velocity; then saturate into the acceleration limits */
    double lb_pv = fmax(lb_p, lb_v), ub_pv = fmin(ub_p, ub_v);
    double lb = fmax(lb_pv, lb_s), ub = fmin(ub_pv, ub_s);
    if (ub < lb) { lb = lb_pv; ub = ub_pv; }
    if (ub < lb) { lb = lb_p; ub = ub_p; }
    *lb_out = fmin(fmax(lb, -ddq_max), ddq_max);
    *ub_out = fmin(fmax(ub, -ddq_max), ddq_max);
}

/* JointLimitsViability.bounds_for (with stopping_deceleration) and safe_acceleration. */
static void viable_bounds(const a3cqp_params *p, const double *q, const double *qd, const double *M, const double *bias,
                          double *lb, double *ub, double *safe) {
    for (int i = 0; i < 7; i++) {
        double stop = p->ddq_max[i];
        if (p->has_tau_stop != 0.0) {
            double room = fmax(p->tau_stop_max[i] - fabs(bias[i]), 0.0);
            stop = fmax(fmin(p->torque_share * room / M[i * 8], p->stop_share * p->ddq_max[i]),
                        p->min_stop_fraction * p->ddq_max[i]);
        }
        joint_bounds(q[i], qd[i], p->q_min[i], p->q_max[i], p->dq_max[i], p->ddq_max[i], stop, p->horizon,
                     &lb[i], &ub[i]);
        safe[i] = fmin(fmax(-p->brake_gain * qd[i], lb[i]), ub[i]);
    }
}

/* ------------------------------------------------------------------ one arm: tasks, P, c, G, h */

static void assemble_one(const a3cqp_params *p, const double *q, const double *qd, const double *M, const double *bias,
                         const double *J, const double *jdqd, const double *twist, const double *pos, const double *rot,
                         const double *w, const double *f_d, const double *pos_d, const double *rot_d,
                         const double *f_ext, int contact, int count_ext, const double *q_des, const double *qd_des,
                         const double *cost, double *P, double *c, double *G, double *h, double *pd_out, double *pose_out,
                         double *f_adm, double *f_ctc, double *safe) {
    context cx;
    build_context(p, q, qd, M, J, pos, rot, w, f_d, pos_d, rot_d, q_des, qd_des, &cx);
    const double *W1 = cx.W[0], *W2 = cx.W[1], *W3 = cx.W[2];

    /* Admittance.admittance_wrench (eq. 16-18) */
    double v[6];
    for (int i = 0; i < 6; i++)
        v[i] = (p->ac_paper != 0.0 ? f_ext[i] : f_ext[i] - p->c_d * twist[i]) / p->lambda_d - jdqd[i];
    mv(6, 6, cx.lam, v, f_adm);
    for (int i = 0; i < 6; i++) f_adm[i] -= f_ext[i] + (p->ac_paper != 0.0 ? p->c_d * twist[i] : 0.0);
    /* ForceControl.contact_wrench (eq. 20) */
    mv(6, 6, cx.D, cx.fdl, f_ctc);
    /* A3CQPController.wrench_feedforward (eq. 24b per local axis), zero in contact */
    double f_ff[6] = {0};
    if (p->wrench_ff != 0.0 && !contact) {
        double la[6], lc[6], r[6];
        mtv(6, 6, cx.D, f_adm, la);
        mtv(6, 6, cx.D, f_ctc, lc);
        for (int i = 0; i < 6; i++)
            r[i] = (w[i * 3 + 1] * la[i] + w[i * 3 + 2] * lc[i])
                   / (w[i * 3 + 1] + w[i * 3 + 2] + p->reg + (p->wrench_sum != 0.0 ? w[i * 3] : 0.0));
        mv(6, 6, cx.D, r, f_ff);
    }
    /* CartesianIK (eq. 10-11): J q̈ = ẍ_d − J̇q̇ − Λ⁻¹ f_ff */
    double b_ik[6], lf[6];
    mv(6, 6, cx.lam_inv, f_ff, lf);
    for (int i = 0; i < 6; i++) b_ik[i] = p->kp[i] * cx.pose_err[i] - p->kv[i] * twist[i] - jdqd[i] - lf[i];
    /* JointCentering (eq. 23) */
    double b_jc[7], sk = 2.0 * sqrt(p->kq);
    for (int i = 0; i < 7; i++) b_jc[i] = p->kq * (p->q_center[i] - q[i]) - sk * qd[i];

    /* q̈ block: Jᵀ (W1 + γ(I − W1)) J, −Jᵀ W1 b_ik (IK and the regularizer share A = J), + the JC weight */
    /* cost[0..2]: IK, AC, FC's share of this cost (1 1 1: the single QP; a population's level: 0 or 1 per arm) */
    double Wg[36], wb[6], WJ[42], Hqq[49], gqq[7], Wjc[49], wjb[7];
    /* tasks.regularizer_ik_weight: the regularizer leaves out D min(w1, 1) Dᵀ (an IK weight above 1 would make its
       weight negative, and a level holding it alone non-convex); W1 itself wherever w1 ≤ 1 */
    const double *W1r = W1;
    double W1c[36];
    int over = 0;
    for (int a = 0; a < 6; a++) over |= w[a * 3] > 1.0 + 1e-9;
    if (p->creg_gamma != 0.0 && over) {
        double Dw[36];
        for (int i = 0; i < 6; i++)
            for (int a = 0; a < 6; a++) Dw[i * 6 + a] = cx.D[i * 6 + a] * fmin(w[a * 3], 1.0);
        mm_nt(6, 6, 6, Dw, cx.D, W1c);
        W1r = W1c;
    }
    for (int i = 0; i < 36; i++)
        Wg[i] = cost[0] * W1[i]
                + (p->creg_gamma != 0.0 ? (i % 7 == 0 ? p->creg_gamma : 0.0) - p->creg_gamma * W1r[i] : 0.0);
    mv(6, 6, W1, b_ik, wb);
    for (int i = 0; i < 6; i++) wb[i] *= cost[0];
    mm(6, 6, 7, Wg, J, WJ);
    mm_tn(7, 6, 7, J, WJ, Hqq);
    mtv(7, 6, J, wb, gqq);
    for (int i = 0; i < 49; i++) Wjc[i] = p->jc_eps * cx.jtw1j[i] + p->jc_eps_n * cx.nullspace[i];
    mv(7, 7, Wjc, b_jc, wjb);
    for (int i = 0; i < 49; i++) Hqq[i] += Wjc[i];
    for (int i = 0; i < 7; i++) gqq[i] = -gqq[i] - wjb[i];
    /* f block: AC and FC (A = I): W2 + W3, −(W2 f_adm + W3 f_ctc) */
    double a2[6], a3[6];
    mv(6, 6, W2, f_adm, a2);
    mv(6, 6, W3, f_ctc, a3);
    for (int i = 0; i < 6; i++) { a2[i] *= cost[1]; a3[i] *= cost[2]; }
    /* wrench_blend "weighted_sum": + W1 (IK's zero-wrench reference, A3CQPController._ik_wrench) */
    double Wf[36];
    for (int i = 0; i < 36; i++) Wf[i] = (cost[1] * W2[i] + cost[2] * W3[i]) + (p->wrench_sum != 0.0 ? cost[0] * W1[i] : 0.0);
    /* A3CQPController._assemble: P = ½ (H + Hᵀ) + r I on the block diagonal, c */
    memset(P, 0, sizeof(double) * NV * NV);
    for (int i = 0; i < 7; i++)
        for (int j = 0; j < 7; j++) P[i * NV + j] = 0.5 * (Hqq[i * 7 + j] + Hqq[j * 7 + i]);
    for (int i = 0; i < 6; i++)
        for (int j = 0; j < 6; j++) P[(i + 7) * NV + j + 7] = 0.5 * (Wf[i * 6 + j] + Wf[j * 6 + i]);
    for (int i = 0; i < NV; i++) P[i * NV + i] += p->reg;
    for (int i = 0; i < 7; i++) c[i] = gqq[i];
    for (int i = 0; i < 6; i++) c[7 + i] = -(a2[i] + a3[i]);

    /* JointLimitsViability.rows: (I + ∂q̈_pd/∂q̈*) q̈* + q̈_pd0 ∈ [lb, ub], and the total with B⁻¹Jᵀ f */
    double lb[7], ub[7];
    viable_bounds(p, q, qd, M, bias, lb, ub, safe);
    double *g = G, *hh = h;
    double off[7];
    memcpy(off, cx.qdd_pd0, sizeof off);
    if (p->include_f_ext != 0.0 || count_ext) { /* for every arm, or for this one (the step's f_ext_limits) */
        double t[7];
        mv(7, 6, cx.binv_jt, f_ext, t);
        for (int i = 0; i < 7; i++) off[i] += t[i];
    }
    int sets = p->target_total != 0.0 ? 4 : 2;
    for (int s = 0; s < sets; s++) {
        double sign = (s % 2 == 0) ? 1.0 : -1.0;
        int total = s >= 2;
        for (int i = 0; i < 7; i++, g += NV, hh++) {
            for (int j = 0; j < 7; j++) g[j] = sign * cx.qdd_map[i * 7 + j];
            for (int j = 0; j < 6; j++) g[7 + j] = total ? sign * cx.binv_jt[i * 6 + j] : 0.0;
            double o = total ? off[i] : cx.qdd_pd0[i];
            *hh = sign > 0 ? ub[i] - o : o - lb[i];
        }
    }
    /* WrenchBox: ±f ≤ f̄ */
    for (int s = 0; s < 2; s++)
        for (int i = 0; i < 6; i++, g += NV, hh++) {
            memset(g, 0, sizeof(double) * NV);
            g[7 + i] = s == 0 ? 1.0 : -1.0;
            *hh = p->wrench_max[i];
        }
    /* FrictionPyramid (eq. 9): U(μ) Rᵀ f ≤ 0 in contact, 0 ≤ 1 otherwise */
    static const double U[4][2] = {{1.0, 0.0}, {-1.0, 0.0}, {0.0, 1.0}, {0.0, -1.0}};
    for (int r = 0; r < 4; r++, g += NV, hh++) {
        memset(g, 0, sizeof(double) * NV);
        if (contact)
            for (int j = 0; j < 3; j++) /* (U Rᵀ)_rj = Σ_a U_ra R_ja */
                g[7 + j] = U[r][0] * rot[j * 3 + 0] + U[r][1] * rot[j * 3 + 1] + (-p->mu) * rot[j * 3 + 2];
        *hh = contact ? 0.0 : 1.0;
    }
    /* TorqueLimits: ±(B (I + ∂q̈_pd/∂q̈*) q̈* + Jᵀ f) ≤ τ̄ ∓ (B q̈_pd0 + h + g), τ̄ ≥ |τ of the brake| */
    if (p->has_torque_limits != 0.0) {
        double Mg[49], toff[7], ts[7];
        mm(7, 7, 7, M, cx.qdd_map, Mg);
        mv(7, 7, M, cx.qdd_pd0, toff);
        mv(7, 7, M, safe, ts);
        for (int s = 0; s < 2; s++) {
            double sign = s == 0 ? 1.0 : -1.0;
            for (int i = 0; i < 7; i++, g += NV, hh++) {
                for (int j = 0; j < 7; j++) g[j] = sign * Mg[i * 7 + j];
                for (int j = 0; j < 6; j++) g[7 + j] = sign * J[j * 7 + i];
                double o = toff[i] + bias[i];
                double lim = p->torque_max[i];
                if (p->torque_safe != 0.0) lim = fmax(lim, fabs(ts[i] + bias[i]));
                *hh = lim - sign * o;
            }
        }
    }
    memcpy(pd_out, cx.pd, sizeof cx.pd);
    memcpy(pose_out, cx.pose_err, sizeof cx.pose_err);
}

/* The packed per-arm input row of a3cqp_assemble: (name, width) in order; the bindings pack by this table. */
#define A3CQP_INPUTS(A)                                                                                            \
    A(q, 7) A(qd, 7) A(mass, 49) A(bias, 7) A(jac, 42) A(jdot_qdot, 6) A(twist, 6) A(pos, 3) A(rot, 9)             \
    A(weights, 18) A(f_d, 6) A(pos_d, 3) A(rot_d, 9) A(f_ext, 6) A(in_contact, 1) A(q_des, 7) A(qd_des, 7)        \
    A(f_ext_limits, 1)
typedef struct { A3CQP_INPUTS(DECLARE_A) } a3cqp_input;
#define IN(f) (int)(offsetof(a3cqp_input, f) / sizeof(double))
enum {
    IN_Q = IN(q), IN_QD = IN(qd), IN_M = IN(mass), IN_BIAS = IN(bias), IN_J = IN(jac), IN_JDQD = IN(jdot_qdot),
    IN_TWIST = IN(twist), IN_POS = IN(pos), IN_ROT = IN(rot), IN_W = IN(weights), IN_FD = IN(f_d),
    IN_POSD = IN(pos_d), IN_ROTD = IN(rot_d), IN_FEXT = IN(f_ext), IN_CONTACT = IN(in_contact), IN_QDES = IN(q_des),
    IN_QDDES = IN(qd_des), IN_FEXTLIM = IN(f_ext_limits), IN_SIZE = (int)(sizeof(a3cqp_input) / sizeof(double))
};
#define INPUT_FIELD(f, n) {#f, IN(f), n},
static const a3cqp_field INPUT_FIELDS[] = { A3CQP_INPUTS(INPUT_FIELD) };

int64_t a3cqp_input_fields(const a3cqp_field **out) {
    *out = INPUT_FIELDS;
    return (int64_t)(sizeof(INPUT_FIELDS) / sizeof(INPUT_FIELDS[0]));
}

int64_t a3cqp_input_size(void) { return IN_SIZE; }

/* A3CQPController.build_context + build_qp for n arms.  in: n rows of IN_SIZE doubles.  out, one array after the
 * other: P [n 13 13], c [n 13], G [n m 13], h [n m] (m = a3cqp_rows(p)), then what the step needs afterwards:
 * pd = P W1 J [n 7 7], e_x [n 6], f_adm [n 6], f_ctc [n 6], the viable brake q̈_safe [n 7]. */
static const double ALL_COSTS[3] = {1.0, 1.0, 1.0};

void a3cqp_assemble(int64_t n, const a3cqp_params *p, const double *in, double *out) {
    int64_t m = a3cqp_rows(p);
    double *P = out, *c = P + NV * NV * n, *G = c + NV * n, *h = G + m * NV * n, *pd = h + m * n;
    double *pose = pd + 49 * n, *f_adm = pose + 6 * n, *f_ctc = f_adm + 6 * n, *safe = f_ctc + 6 * n;
    for (int64_t k = 0; k < n; k++) {
        const double *a = in + IN_SIZE * k;
        assemble_one(p, a + IN_Q, a + IN_QD, a + IN_M, a + IN_BIAS, a + IN_J, a + IN_JDQD, a + IN_TWIST, a + IN_POS,
                     a + IN_ROT, a + IN_W, a + IN_FD, a + IN_POSD, a + IN_ROTD, a + IN_FEXT, a[IN_CONTACT] != 0.0,
                     a[IN_FEXTLIM] != 0.0, a + IN_QDES, a + IN_QDDES, ALL_COSTS, P + NV * NV * k, c + NV * k, G + m * NV * k, h + m * k, pd + 49 * k,
                     pose + 6 * k, f_adm + 6 * k, f_ctc + 6 * k, safe + 7 * k);
    }
}

/* a3cqp_assemble for a population: arm k runs with the parameters p, its row robot[k] (a3cqp_robot) replacing the
 * per-robot fields and scaling the task costs.  Same outputs. */
void a3cqp_assemble_robots(int64_t n, const a3cqp_params *p, const double *in, const double *robot, double *out) {
    int64_t m = a3cqp_rows(p);
    double *P = out, *c = P + NV * NV * n, *G = c + NV * n, *h = G + m * NV * n, *pd = h + m * n;
    double *pose = pd + 49 * n, *f_adm = pose + 6 * n, *f_ctc = f_adm + 6 * n, *safe = f_ctc + 6 * n;
    const int64_t R = (int64_t)(sizeof(a3cqp_robot) / sizeof(double));
    for (int64_t k = 0; k < n; k++) {
        const double *a = in + IN_SIZE * k;
        const a3cqp_robot *r = (const a3cqp_robot *)(robot + R * k);
        a3cqp_params pk = *p;
        memcpy(pk.kp, r->kp, sizeof pk.kp);
        memcpy(pk.kv, r->kv, sizeof pk.kv);
        pk.lambda_d = r->lambda_d;
        pk.c_d = r->c_d;
        pk.kq = r->kq;
        pk.jc_eps = r->jc_eps;
        pk.jc_eps_n = r->jc_eps_n;
        pk.creg_gamma = r->creg_gamma;
        const double cost[3] = {r->cost_ik, r->cost_ac, r->cost_fc};
        assemble_one(&pk, a + IN_Q, a + IN_QD, a + IN_M, a + IN_BIAS, a + IN_J, a + IN_JDQD, a + IN_TWIST, a + IN_POS,
                     a + IN_ROT, a + IN_W, a + IN_FD, a + IN_POSD, a + IN_ROTD, a + IN_FEXT, a[IN_CONTACT] != 0.0,
                     a[IN_FEXTLIM] != 0.0, a + IN_QDES, a + IN_QDDES, cost, P + NV * NV * k, c + NV * k, G + m * NV * k, h + m * k,
                     pd + 49 * k, pose + 6 * k, f_adm + 6 * k, f_ctc + 6 * k, safe + 7 * k);
    }
}

/* ------------------------------------------------------------------ after the QP: controller._torque_law, _finish */

/* Eq. 4-7 from x = (q̈*, f) [n 13] where ok[k], else the fallback brake (q̈ = q̈_safe, f = 0, τ = B q̈_safe + h + g,
 * q* = q, q̇* = q̇); then q*, q̇* relax toward (q, q̇) where IK is off, and τ is clipped to ±τ_max (NaN → 0).
 * in, asm: a3cqp_assemble's input and output; leak_extra [n 6]: the extra per-axis relaxation rate of leak_per_axis
 * (1/s; NULL: none).  out, one array after the other: τ, q̈*, f, q̈_pd, q*, q̇* [n 7 / 6]
 * and saturated [n] (1.0 where some |τ_i| exceeded τ_max). */
/* controller._relax_min_w1: q*, q̇* toward (q, q̇) at rate leak (1 − min_i w1_i), every joint. */
static void relax_min_w1(const a3cqp_params *p, const double *w, const double *q, const double *qd, double *qs,
                         double *qds) {
    double w1_min = w[0];
    for (int i = 1; i < 6; i++) w1_min = fmin(w1_min, w[i * 3]);
    double rate = clampd(p->leak * (1.0 - clampd(w1_min, 0.0, 1.0)), 0.0, 1.0);
    for (int i = 0; i < 7; i++) {
        qs[i] -= rate * (qs[i] - q[i]);
        qds[i] -= rate * (qds[i] - qd[i]);
    }
}

/* controller._relax_per_axis: the task-space part of q* − q relaxed at rate leak (w2 + w3 min(1, f_d / 1 N))
 * + Δt extra_i along each axis of L (extra [6] in 1/s, or NULL for none), the null-space part at rate leak (same for
 * q̇*). */
static void relax_per_axis(const a3cqp_params *p, const double *J, const double *rot, const double *w,
                           const double *f_d, const double *extra, const double *q, const double *qd, double *qs,
                           double *qds) {
    double jjt[36], jjt_inv[36], jpinv[7 * 6], r[6];
    mm_nt(6, 7, 6, J, J, jjt);
    for (int i = 0; i < 6; i++) jjt[i * 6 + i] += p->nullspace_damping;
    gj_solve(6, jjt, 0, NULL, jjt_inv);
    mm_tn(7, 6, 6, J, jjt_inv, jpinv);
    for (int i = 0; i < 6; i++) {
        double fd = clampd(clampd(f_d[i], 0.0, p->f_d_max), 0.0, 1.0);
        double ri = p->leak * (w[i * 3 + 1] + w[i * 3 + 2] * fd);
        if (extra) ri += p->dt * extra[i];
        r[i] = clampd(ri, 0.0, 1.0);
    }
    double full = fmin(p->leak, 1.0);
    double *des[2] = {qs, qds};
    const double *meas[2] = {q, qd};
    for (int s = 0; s < 2; s++) {
        double d[7], dx[6], dl[6], back[6], task[7], corr[7];
        for (int i = 0; i < 7; i++) d[i] = des[s][i] - meas[s][i];
        mv(6, 7, J, d, dx);
        for (int b = 0; b < 2; b++) { /* local = Rᵀ dx per 3-block, scaled, back = R local (eq. 3) */
            for (int i = 0; i < 3; i++) {
                dl[3 * b + i] = 0.0;
                for (int j = 0; j < 3; j++) dl[3 * b + i] += rot[j * 3 + i] * dx[3 * b + j];
                dl[3 * b + i] *= r[3 * b + i];
            }
            for (int i = 0; i < 3; i++) {
                back[3 * b + i] = 0.0;
                for (int j = 0; j < 3; j++) back[3 * b + i] += rot[i * 3 + j] * dl[3 * b + j];
            }
        }
        mv(7, 6, jpinv, dx, task);
        mv(7, 6, jpinv, back, corr);
        for (int i = 0; i < 7; i++) des[s][i] -= corr[i] + full * (d[i] - task[i]);
    }
}

void a3cqp_torque(int64_t n, const a3cqp_params *p, const double *in, const double *asm_out, const double *x,
                  const uint8_t *ok, const double *leak_extra, double *out) {
    const double dt = p->dt;
    int64_t m = a3cqp_rows(p);
    const double *pd = asm_out + (NV * NV + NV + m * NV + m) * n, *safe = pd + (49 + 6 + 6 + 6) * n;
    double *tau = out, *qdd = tau + 7 * n, *f = qdd + 7 * n, *qdd_pd = f + 6 * n, *q_des = qdd_pd + 7 * n;
    double *qd_des = q_des + 7 * n, *saturated = qd_des + 7 * n;
    for (int64_t k = 0; k < n; k++) {
        const double *a = in + IN_SIZE * k;
        const double *qk = a + IN_Q, *qdk = a + IN_QD, *Mk = a + IN_M, *Jk = a + IN_J, *wk = a + IN_W;
        const double *bk = a + IN_BIAS, *qs = a + IN_QDES, *qds = a + IN_QDDES;
        double *tk = tau + 7 * k, *ak = qdd + 7 * k, *fk = f + 6 * k, *pk = qdd_pd + 7 * k;
        double qn[7], qdn[7], acc[7];
        if (ok[k]) {
            const double *xk = x + NV * k;
            double e[7], jf[7];
            for (int i = 0; i < 7; i++) {
                ak[i] = xk[i];
                qdn[i] = qds[i] + dt * ak[i];
                qn[i] = qs[i] + dt * qds[i] + (0.5 * dt * dt) * ak[i];
                e[i] = p->cv * (qdn[i] - qdk[i]) + p->cp * (qn[i] - qk[i]);
            }
            for (int i = 0; i < 6; i++) fk[i] = xk[7 + i];
            mv(7, 7, pd + 49 * k, e, pk);
            for (int i = 0; i < 7; i++) acc[i] = ak[i] + pk[i];
            mv(7, 7, Mk, acc, tk);
            mtv(7, 6, Jk, fk, jf);
            for (int i = 0; i < 7; i++) tk[i] += jf[i] + bk[i];
        } else {
            memcpy(ak, safe + 7 * k, sizeof(double) * 7);
            mv(7, 7, Mk, ak, tk);
            for (int i = 0; i < 7; i++) {
                tk[i] += bk[i];
                pk[i] = 0.0;
                qn[i] = qk[i];
                qdn[i] = qdk[i];
            }
            memset(fk, 0, sizeof(double) * 6);
        }
        if (p->leak_per_axis != 0.0)
            relax_per_axis(p, Jk, a + IN_ROT, wk, a + IN_FD, leak_extra ? leak_extra + 6 * k : NULL, qk, qdk, qn, qdn);
        else relax_min_w1(p, wk, qk, qdk, qn, qdn);
        for (int i = 0; i < 7; i++) {
            q_des[7 * k + i] = qn[i];
            qd_des[7 * k + i] = qdn[i];
        }
        double sat = 0.0;
        for (int i = 0; i < 7; i++) {
            double t = tk[i], lim = p->tau_clip[i];
            if (fabs(t) > lim) sat = 1.0;
            tk[i] = t != t ? 0.0 : clampd(t, -lim, lim);
        }
        saturated[k] = sat;
    }
}
