/* The eq. 35 point mass in C: a copy of envs/point_mass.py for the C A2C iteration and the gym env, where a torch
 * call per step would cost more than the step; tests/test_point_mass_native.py and tests/test_a2c_native.py keep it
 * equal to the torch env.
 *
 * Function by function, in the torch code's order of operations:
 *   pm_agent_step  agent_step (eq. 29 on the action, `substeps` x eq. 35, eq. 30 reward)
 *   pm_observe     observe_state (eq. 26 observation, + privileged_state)
 *   pm_auto_reset  auto_reset (switch to the pending episode)
 * Physics in double, observations in float, as the torch env.  Header-only (static functions) so the A2C
 * iteration inlines them; envs/native/point_mass.c exports a batched step for Python.
 */
#ifndef A3CQP_POINT_MASS_H
#define A3CQP_POINT_MASS_H

#include <math.h>
#include <stdint.h>

/* PointMassConfig, AdaptationConfig and RewardConfig values (envs/native/__init__.py: PMParams, field by field) */
typedef struct {
    int64_t N, episode_steps, substeps, sched_len;
    double mass, kp, kv, physics_dt, lambda_d, c_d, wall_stiffness, wall_damping, operator_v_hand, operator_grip_min;
    int64_t operator_drag; /* operator_model 'drag' (1) or 'push' (0) */
    double sigma_w, sigma_f, adapt_dt, f_d_max, e_max, f_env_max, f_ope_max;
    double alpha[4];
} pm_params;

/* The state dict of the torch env, one array per entry (w_logits [N, 3]); a pending episode uses only the
 * EPISODE_KEYS entries (target, wall, has_wall, scen, wlog, fd). */
typedef struct {
    double *x, *xd, *target, *wlog, *fd, *wall, *fenv, *fope;
    uint8_t *has_wall;
    int64_t *t, *scen, *slot;
} pm_state;

#define PM_PRIVILEGED_DIM 11 /* PRIVILEGED_DIM of envs/point_mass.py */

static inline double pm_clamp(double v, double lo, double hi) { return v < lo ? lo : (v > hi ? hi : v); }
static inline double pm_clip01(double v) { return pm_clamp(v, 0.0, 1.0); }

/* eq. 29e: task weights from the pre-softmax w̌ [3] */
static inline void pm_softmax3(const double *wl, double *w) {
    double m = fmax(fmax(wl[0], wl[1]), wl[2]), sum = 0.0;
    for (int k = 0; k < 3; k++) { w[k] = exp(wl[k] - m); sum += w[k]; }
    for (int k = 0; k < 3; k++) w[k] /= sum;
}

/* observe_state for env i: eq. 26 observation [3], then with `privileged` privileged_state [PM_PRIVILEGED_DIM] */
static inline void pm_observe(const pm_params *P, const pm_state *s, int64_t i, int privileged, float *out) {
    double e = s->target[i] - s->x[i];
    out[0] = (float)pm_clip01(fabs(e) / P->e_max);
    out[1] = (float)pm_clip01(fabs(s->fenv[i]) / P->f_env_max);
    out[2] = (float)pm_clip01(fabs(s->fope[i]) / P->f_ope_max);
    if (!privileged) return;
    double w[3];
    pm_softmax3(s->wlog + 3 * i, w);
    for (int k = 0; k < 3; k++) out[3 + k] = (float)w[k];
    double has_wall = s->has_wall[i] ? 1.0 : 0.0;
    double has_op = (s->scen[i] == 1 || s->scen[i] == 3) ? 1.0 : 0.0;
    out[6] = (float)(s->fd[i] / P->f_d_max);
    out[7] = (float)pm_clamp(e / P->e_max, -1.0, 1.0);
    out[8] = (float)pm_clamp(s->fenv[i] / P->f_env_max, -1.0, 1.0);
    out[9] = (float)pm_clamp(s->fope[i] / P->f_ope_max, -1.0, 1.0);
    out[10] = (float)tanh(s->xd[i]);
    out[11] = (float)has_wall;
    out[12] = (float)has_op;
    out[13] = (float)(has_wall * pm_clamp((s->wall[i] - s->x[i]) / P->e_max, -1.0, 1.0));
}

/* agent_step for env i with action a [4] (clipped to [-1, 1] here, as eq. 29 does); `sched` [2, N, sched_len] holds
 * the operator's intent force per agent step for both episode slots.  Returns the eq. 30 reward. */
static inline double pm_agent_step(const pm_params *P, const pm_state *s, const double *sched, int64_t i,
                                   const float *a) {
    double half = 0.5 * P->sigma_w, *wl = s->wlog + 3 * i, w[3];
    for (int k = 0; k < 3; k++)  /* eq. 29a-c */
        wl[k] = pm_clamp(wl[k] + P->sigma_w * P->adapt_dt * pm_clamp((double)a[k], -1.0, 1.0), -half, half);
    pm_softmax3(wl, w);
    double fd = pm_clamp(s->fd[i] + P->sigma_f * P->adapt_dt * pm_clamp((double)a[3], -1.0, 1.0), 0.0, P->f_d_max);
    int64_t t = s->t[i], tt = t < P->sched_len - 1 ? t : P->sched_len - 1;
    double f_cmd = sched[(s->slot[i] * P->N + i) * P->sched_len + tt];
    double sgn = (f_cmd > 0.0) - (f_cmd < 0.0);
    double mass = P->mass, adm = mass / P->lambda_d - 1.0, dt = P->physics_dt;
    double x = s->x[i], v = s->xd[i], target = s->target[i], wall = s->wall[i], f_env = 0.0, f_ope = 0.0;
    int has_wall = s->has_wall[i] != 0;
    for (int64_t k = 0; k < P->substeps; k++) {
        double pen = x - wall;
        /* unilateral wall: pushes back only */
        f_env = (has_wall && pen > 0.0) ? fmin(-P->wall_stiffness * pen - P->wall_damping * v, 0.0) : 0.0;
        if (P->operator_drag)  /* a hand moving at f_cmd / b through a viscous grip b = f̄_ope / v_hand */
            f_ope = f_cmd != 0.0 ? pm_clamp(f_cmd - P->f_ope_max / P->operator_v_hand * v, -P->f_ope_max, P->f_ope_max)
                                 : 0.0;
        else  /* linear force-velocity law */
            f_ope = f_cmd * pm_clamp(1.0 - v * sgn / P->operator_v_hand, P->operator_grip_min, 1.0);
        double f_ext = f_env + f_ope, e = target - x;
        double acc = (f_ext + w[0] * mass * (P->kp * e - P->kv * v) + w[1] * (adm * f_ext - P->c_d * v) + w[2] * fd) / mass;
        v = v + acc * dt;  /* eq. 35, semi-implicit Euler */
        x = x + v * dt;
    }
    s->x[i] = x; s->xd[i] = v; s->fd[i] = fd; s->fenv[i] = f_env; s->fope[i] = f_ope; s->t[i] = t + 1;
    const double *al = P->alpha;  /* eq. 30 */
    return -al[0] * pm_clip01(fabs(target - x) / P->e_max) - al[1] * pm_clip01(fabs(f_ope) / P->f_ope_max)
           + al[2] * pm_clip01(fabs(f_env) / P->f_env_max) - al[3] * pm_clip01(fabs(fd) / P->f_d_max);
}

/* auto_reset for env i: switch to the pending episode p (dynamics zeroed, schedule slot flipped) */
static inline void pm_auto_reset(const pm_state *s, const pm_state *p, int64_t i) {
    s->target[i] = p->target[i]; s->wall[i] = p->wall[i]; s->has_wall[i] = p->has_wall[i];
    s->scen[i] = p->scen[i]; s->fd[i] = p->fd[i];
    for (int k = 0; k < 3; k++) s->wlog[3 * i + k] = p->wlog[3 * i + k];
    s->x[i] = 0.0; s->xd[i] = 0.0; s->t[i] = 0; s->fenv[i] = 0.0; s->fope[i] = 0.0;
    s->slot[i] = 1 - s->slot[i];
}

#endif
