/* The simulated operator's hand in one call per control period (envs/native/hand.py binds it).

   `hand_wrench` is envs.scenarios.Operator.wrench: a delayed, bounded spring-damper at the handle that pulls it
   toward an attractor moving from the grasp point to the goal, with the grip fading in and out, and a rotational
   spring to the grasped orientation. `hand_push` is PandaSim.push of that wrench at the handle site: a body force
   (xfrc_applied, at the body's centre of mass) and its joint torques Jᵀ(f; τ), which the simulated joint-torque
   sensors read (tau_ext).

   Why C: at 65 arms the numpy form is ~40 numpy calls per control period (~180 µs of a 1-ms period's ~2.2 ms) for a
   few hundred flops per arm. The same quantities in another order (numpy's atan2 and 3 × 3 products round
   differently): they agree with the numpy path to round-off (tests/test_hand_native.py); the numpy path stays the
   reference. No MuJoCo headers: the caller passes the addresses of the mjData arrays it reads and writes. */
#include <math.h>
#include <stddef.h>
#include <stdint.h>

typedef struct {
  int64_t n, lag;
  /* OperatorConfig (stiffness N/m, damping N s/m, rot_stiffness N m/rad, rot_damping N m s/rad, speed m/s,
     grip_time s, max_force N, max_torque N m, noise N) */
  double stiffness, damping, intrinsic_damping, rot_stiffness, rot_damping, speed, grip_time, max_force, max_torque,
      noise;
  /* the operator's state [n]: IDLE 0, HOLD 1, RELEASE 2; times of grasp and release (s); grasp point and goal
     [n, 3]; grasped orientation [n, 3, 3]; per-arm factor on gains and bounds; whether the history is primed */
  const int64_t* state;
  const double *t_grasp, *t_release, *start, *goal, *rot_grasp, *force_scale;
  uint8_t* primed;
  double* hist; /* ring buffer [lag, n, 18] of the handle's (p, v, R, ω) */
} hand_args;

typedef struct {
  int64_t n;
  /* mjData arrays read: site_xpos, xipos, subtree_com, cdof; written: xfrc_applied */
  const double *site_xpos, *xipos, *subtree_com, *cdof;
  double* xfrc_applied;
  /* per arm: the handle site, its body, that body's root [n]; dof addresses [n, 7] */
  const int64_t *site, *body, *root, *dadr;
  const double* mask; /* [7]: 1 for the joints that move the body, 0 for the others; NULL: all */
  double* tau_push;   /* [n, 7]: the pushes' joint torques, added to tau_ext after mj_step2 */
} push_args;

static void cross(const double* a, const double* b, double* out) {
  out[0] = a[1] * b[2] - a[2] * b[1];
  out[1] = a[2] * b[0] - a[0] * b[2];
  out[2] = a[0] * b[1] - a[1] * b[0];
}

static double norm3(const double* v) { return sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]); }

static double clip01(double x) { return x < 0.0 ? 0.0 : (x > 1.0 ? 1.0 : x); }

/* v ← v · min(1, bound / |v|) (envs.scenarios._clip_norm) */
static void clip_norm(double* v, double bound) {
  double n = norm3(v);
  double s = bound / (n > 1e-12 ? n : 1e-12);
  if (s > 1.0) s = 1.0;
  for (int k = 0; k < 3; k++) v[k] *= s;
}

/* Rotation vector of R (a3cqp_rl.control.frames.rotation_log): θ / sin θ times the vee of (R − Rᵀ) / 2. */
static void rotation_log(const double* R, double* out) {
  double v[3] = {0.5 * (R[7] - R[5]), 0.5 * (R[2] - R[6]), 0.5 * (R[3] - R[1])};
  double s = norm3(v);
  double c = 0.5 * (R[0] + R[4] + R[8] - 1.0);
  double theta = atan2(s, c);
  double scale = s > 1e-9 ? theta / (s > 1e-12 ? s : 1e-12) : 1.0 + theta * theta / 6.0;
  for (int k = 0; k < 3; k++) out[k] = scale * v[k];
}

/* force, torque [n, 3] (N, N m; world) of the hands at time t [n] (s; plus `t_add`), from the handle's pose
   pos [n, 3] / rot [n, 3, 3] and its velocity (v + ω × r: twist [n, 6] of the tool tip, r [n, 3] the handle from
   the tip) as they were `lag` periods ago (ring slot k, then overwritten with the present); noise [n, 3] standard
   normal draws at stride `noise_stride` (NULL: none). */
void hand_wrench(const hand_args* a, int64_t k, const double* t, double t_add, const double* pos,
                 const double* twist, const double* r, const double* rot, const double* noise, int64_t noise_stride,
                 double* force, double* torque) {
  const int64_t n = a->n;
  for (int64_t i = 0; i < n; i++) {
    double present[18], old[18], vel[3];
    const double* w = twist + 6 * i + 3;
    cross(w, r + 3 * i, vel);
    for (int j = 0; j < 3; j++) {
      present[j] = pos[3 * i + j];
      present[3 + j] = twist[6 * i + j] + vel[j];
      present[15 + j] = w[j];
    }
    for (int j = 0; j < 9; j++) present[6 + j] = rot[9 * i + j];
    if (!a->primed[i]) { /* no history yet: the hand sees the present */
      for (int64_t s = 0; s < a->lag; s++)
        for (int j = 0; j < 18; j++) a->hist[(s * n + i) * 18 + j] = present[j];
      a->primed[i] = 1;
    }
    double* slot = a->hist + (k * n + i) * 18;
    for (int j = 0; j < 18; j++) {
      old[j] = slot[j];
      slot[j] = present[j];
    }
    double* f = force + 3 * i;
    double* tq = torque + 3 * i;
    if (a->state[i] == 0) {
      for (int j = 0; j < 3; j++) f[j] = tq[j] = 0.0;
      continue;
    }
    double ti = t[i] + t_add;
    double grip = a->state[i] == 1 ? clip01((ti - a->t_grasp[i]) / a->grip_time)
                                   : clip01(1.0 - (ti - a->t_release[i]) / a->grip_time);
    double sc = a->force_scale[i];
    /* the attractor: from the grasp point toward the goal at `speed` */
    const double* st = a->start + 3 * i;
    double path[3];
    for (int j = 0; j < 3; j++) path[j] = a->goal[3 * i + j] - st[j];
    double len = norm3(path);
    double s = clip01((ti - a->t_grasp[i]) * a->speed / (len > 1e-9 ? len : 1e-9));
    for (int j = 0; j < 3; j++) {
      double attr = st[j] + s * path[j];
      double fj = sc * (a->stiffness * (attr - old[j]) - a->damping * old[3 + j]);
      if (a->intrinsic_damping > 0) fj -= sc * a->intrinsic_damping * present[3 + j]; /* on the present velocity */
      if (a->noise > 0 && noise) fj += a->noise * noise[noise_stride * i + j];
      f[j] = grip * fj;
    }
    /* R_grasp R_oldᵀ */
    const double* Rg = a->rot_grasp + 9 * i;
    const double* Ro = old + 6;
    double E[9], lg[3];
    for (int p = 0; p < 3; p++)
      for (int q = 0; q < 3; q++) E[3 * p + q] = Rg[3 * p] * Ro[3 * q] + Rg[3 * p + 1] * Ro[3 * q + 1] + Rg[3 * p + 2] * Ro[3 * q + 2];
    rotation_log(E, lg);
    for (int j = 0; j < 3; j++) tq[j] = grip * (sc * (a->rot_stiffness * lg[j] - a->rot_damping * old[15 + j]));
    clip_norm(f, a->max_force * sc);
    clip_norm(tq, a->max_torque * sc);
  }
}

/* PandaSim.push of force, torque [n, 3] (world) at each arm's site: xfrc_applied of its body (force, and the torque
   plus the force's moment about the body's centre of mass) and tau_push += Jᵀ(f; τ) at the site (as mj_applyFT:
   cdof_lin·f + cdof_ang·((p − c_root) × f + τ), masked to the joints that move the body). Returns the arms pushed. */
int64_t hand_push(const push_args* a, const double* force, const double* torque) {
  int64_t pushed = 0;
  for (int64_t i = 0; i < a->n; i++) {
    const double* f = force + 3 * i;
    const double* tq = torque + 3 * i;
    if (f[0] == 0.0 && f[1] == 0.0 && f[2] == 0.0 && tq[0] == 0.0 && tq[1] == 0.0 && tq[2] == 0.0) continue;
    pushed++;
    const double* p = a->site_xpos + 3 * a->site[i];
    const int64_t b = a->body[i];
    double d[3], m[3], moment[3];
    for (int j = 0; j < 3; j++) d[j] = p[j] - a->xipos[3 * b + j];
    cross(d, f, m);
    double* x = a->xfrc_applied + 6 * b;
    for (int j = 0; j < 3; j++) {
      x[j] += f[j];
      x[3 + j] += tq[j] + m[j];
    }
    for (int j = 0; j < 3; j++) d[j] = p[j] - a->subtree_com[3 * a->root[i] + j];
    cross(d, f, moment);
    for (int j = 0; j < 3; j++) moment[j] += tq[j];
    for (int q = 0; q < 7; q++) {
      const double* c = a->cdof + 6 * a->dadr[7 * i + q];
      double tau = (c[3] * f[0] + c[4] * f[1] + c[5] * f[2]) + (c[0] * moment[0] + c[1] * moment[1] + c[2] * moment[2]);
      a->tau_push[7 * i + q] += a->mask ? tau * a->mask[q] : tau;
    }
  }
  return pushed;
}

int64_t hand_args_size(void) { return (int64_t)sizeof(hand_args); }
int64_t push_args_size(void) { return (int64_t)sizeof(push_args); }
