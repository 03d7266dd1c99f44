/* A control period's sensing of N Panda arms in one MuJoCo model, in one call (a3cqp_rl/robot/sense.py binds it).

   `sense_observe` is what PandaSim's numpy path computes after mj_step1 (`_observe_arrays`, `_update_f_env`,
   `_site_kinematics` in sim.py): each arm's joint state, B(q) block, h + g, the F/T reading, the environment wrench
   on the tool from it, and the control site's pose, [Jᵀ | J̇ᵀ], twist and J̇q̇. `sense_wrench` is
   f_ext = J^{T†} τ_ext = Λ J B⁻¹ τ_ext of a3cqp_rl.control.controller.wrench_from_joint_torques (section V-A of the
   paper), with Cholesky factors of B and Λ⁻¹ where numpy solves by LU.

   Why C: at 65 arms the numpy form is ~50 calls of 1-20 µs per control period (~200 µs), for ~3 k flops per arm.
   The same quantities, summed in another order: they agree with the numpy path to round-off (tests/test_sense.py).

   No MuJoCo headers: the caller passes the addresses of the mjData arrays it reads (stable for the data's life). */
#include <math.h>
#include <stddef.h>
#include <stdint.h>

typedef struct {
  int64_t n;
  /* mjData arrays: qpos, qvel, qfrc_bias, the sparse M, sensordata, site_xpos, site_xmat, subtree_com, cacc, cvel,
     cdof, cdof_dot */
  const double *qpos, *qvel, *qfrc_bias, *M, *sensordata, *site_xpos, *site_xmat, *subtree_com, *cacc, *cvel,
      *cdof, *cdof_dot;
  /* per arm: qpos and dof addresses [n, 7], B(q)'s entries in M [n, 49], F/T sensor addresses [n, 6], the F/T
     site, its body and that body's root [n]; the control site and its body [n] (NULL: no control site) */
  const int64_t *qadr, *dadr, *m_idx, *ft_adr, *ft_site, *ft_body, *root_body, *cs, *cs_body;
  const double* cs_mask; /* [7]: 1 for the joints that move the control site, 0 for the others; NULL: all */
  const double* origin;  /* [n, 3]: where each arm's copy sits in the model's world (m) */
  /* mjData's tree_awake [ntree] and each arm's tree [n] (NULL: read every arm). A sleeping arm's data do not change
     (MuJoCo skips its dynamics), so its read-out keeps the values of its last one. */
  const int32_t* tree_awake;
  const int64_t* arm_tree;
  /* outputs [n, ...] */
  double *q, *qd, *bias, *mass, *ft, *f_env, *cs_pos, *cs_rot, *jt, *twist, *jdot_qdot;
  double tool_mass; /* kg: the F/T site's body's subtree (sensor and tool) */
} sense_args;

static void cross(const double* a, const double* b, double* out) {
  out[0] = a[1] * b[2] - a[2] * b[1];
  out[1] = a[2] * b[0] - a[0] * b[2];
  out[2] = a[0] * b[1] - a[1] * b[0];
}

/* Newton on the sensor + tool subtree: F_env = m a_com − m g − R·reading, its moment about the F/T site; the
   subtree's centre-of-mass acceleration from MuJoCo's com-based cacc (gravity in it as −g): lin + α × r + ω × v. */
static void f_env_of(const sense_args* a, int64_t i) {
  const double* R = a->site_xmat + 9 * a->ft_site[i];
  const double* sp = a->site_xpos + 3 * a->ft_site[i];
  const double* com = a->subtree_com + 3 * a->ft_body[i];
  const double* rc = a->subtree_com + 3 * a->root_body[i];
  const double* ca = a->cacc + 6 * a->ft_body[i];
  const double* cv = a->cvel + 6 * a->ft_body[i];
  const double* ft = a->ft + 6 * i;
  double* f = a->f_env + 6 * i;
  double r[3], v[3], t[3], acc[3], support[3], lever[3];
  for (int k = 0; k < 3; k++) r[k] = com[k] - rc[k];
  cross(cv, r, t);
  for (int k = 0; k < 3; k++) v[k] = cv[3 + k] + t[k];
  cross(ca, r, t);
  cross(cv, v, acc);
  for (int k = 0; k < 3; k++) support[k] = a->tool_mass * (ca[3 + k] + t[k] + acc[k]);
  for (int k = 0; k < 3; k++) lever[k] = com[k] - sp[k];
  cross(lever, support, t);
  for (int k = 0; k < 3; k++) {
    double rf = R[3 * k] * ft[0] + R[3 * k + 1] * ft[1] + R[3 * k + 2] * ft[2];
    double rt = R[3 * k] * ft[3] + R[3 * k + 1] * ft[4] + R[3 * k + 2] * ft[5];
    f[k] = support[k] - rf;
    f[3 + k] = t[k] - rt;
  }
}

/* The control site p: column j of J is (v_j + ω_j × r; ω_j), of J̇ (v̇_j + ω̇_j × r + ω_j × v_p; ω̇_j), with
   (ω_j; v_j) = cdof[j], (ω̇_j; v̇_j) = cdof_dot[j], r = p − c (c: the arm's root subtree com) and v_p the site's
   velocity; stored transposed, [Jᵀ | J̇ᵀ] [7, 12]; then ẋ = J q̇ and J̇q̇. */
static void site_kinematics(const sense_args* a, int64_t i) {
  const double* p = a->site_xpos + 3 * a->cs[i];
  const double* xm = a->site_xmat + 9 * a->cs[i];
  const double* rc = a->subtree_com + 3 * a->root_body[i];
  const double* cb = a->cvel + 6 * a->cs_body[i];
  const double* qd = a->qd + 7 * i;
  double* jt = a->jt + 84 * i;
  double r[3], vp[3], t[3], u[3];
  for (int k = 0; k < 3; k++) {
    r[k] = p[k] - rc[k];
    a->cs_pos[3 * i + k] = p[k] - a->origin[3 * i + k];
  }
  for (int k = 0; k < 9; k++) a->cs_rot[9 * i + k] = xm[k];
  cross(cb, r, t);
  for (int k = 0; k < 3; k++) vp[k] = cb[3 + k] + t[k];
  double vel[12] = {0};
  for (int j = 0; j < 7; j++) {
    const double* d = a->cdof + 6 * a->dadr[7 * i + j];
    const double* dd = a->cdof_dot + 6 * a->dadr[7 * i + j];
    double mask = a->cs_mask ? a->cs_mask[j] : 1.0;
    double* row = jt + 12 * j;
    cross(d, r, t);
    for (int k = 0; k < 3; k++) {
      row[k] = (d[3 + k] + t[k]) * mask;
      row[3 + k] = d[k] * mask;
    }
    cross(dd, r, t);
    cross(d, vp, u);
    for (int k = 0; k < 3; k++) {
      row[6 + k] = (dd[3 + k] + t[k] + u[k]) * mask;
      row[9 + k] = dd[k] * mask;
    }
    for (int k = 0; k < 12; k++) vel[k] += qd[j] * row[k];
  }
  for (int k = 0; k < 6; k++) {
    a->twist[6 * i + k] = vel[k];
    a->jdot_qdot[6 * i + k] = vel[6 + k];
  }
}

void sense_observe(const sense_args* a) {
  for (int64_t i = 0; i < a->n; i++) {
    if (a->tree_awake && !a->tree_awake[a->arm_tree[i]]) continue;
    for (int k = 0; k < 7; k++) {
      int64_t dof = a->dadr[7 * i + k];
      a->q[7 * i + k] = a->qpos[a->qadr[7 * i + k]];
      a->qd[7 * i + k] = a->qvel[dof];
      a->bias[7 * i + k] = a->qfrc_bias[dof];
    }
    for (int k = 0; k < 49; k++) a->mass[49 * i + k] = a->M[a->m_idx[49 * i + k]];
    for (int k = 0; k < 6; k++) a->ft[6 * i + k] = a->sensordata[a->ft_adr[6 * i + k]];
    f_env_of(a, i);
    if (a->cs) site_kinematics(a, i);
  }
}

/* In place: the lower Cholesky factor of the symmetric n × n matrix A (its lower triangle read); 0 when A is not
   positive definite (or not finite). */
static int cholesky(double* A, int n) {
  for (int j = 0; j < n; j++) {
    double s = A[j * n + j];
    for (int k = 0; k < j; k++) s -= A[j * n + k] * A[j * n + k];
    if (!(s > 0.0)) return 0;
    double d = sqrt(s);
    A[j * n + j] = d;
    for (int i = j + 1; i < n; i++) {
      double v = A[i * n + j];
      for (int k = 0; k < j; k++) v -= A[i * n + k] * A[j * n + k];
      A[i * n + j] = v / d;
    }
  }
  return 1;
}

/* x ← (L Lᵀ)⁻¹ x for the factor L of `cholesky`. */
static void cho_solve(const double* L, int n, double* x) {
  for (int i = 0; i < n; i++) {
    double v = x[i];
    for (int k = 0; k < i; k++) v -= L[i * n + k] * x[k];
    x[i] = v / L[i * n + i];
  }
  for (int i = n - 1; i >= 0; i--) {
    double v = x[i];
    for (int k = i + 1; k < n; k++) v -= L[k * n + i] * x[k];
    x[i] = v / L[i * n + i];
  }
}

/* out [n, 6] = Λ J B⁻¹ τ with Λ⁻¹ = J B⁻¹ Jᵀ + damping I, per arm; tau [n, 7] and mass [n, 7, 7] C-contiguous, jac
   [n, 6, 7] read with element strides (s0, s1, s2). An arm with τ = 0 gets 0 (nothing pushes it), one whose B or Λ⁻¹
   is not positive definite (NaN in its inputs) NaN. */
void sense_wrench(int64_t n, const double* tau, const double* jac, int64_t s0, int64_t s1, int64_t s2,
                  const double* mass, double damping, double* out) {
  for (int64_t i = 0; i < n; i++) {
    const double* t = tau + 7 * i;
    double* o = out + 6 * i;
    int live = 0;
    for (int k = 0; k < 7; k++) live |= (t[k] != 0.0);  /* NaN != 0: it propagates */
    if (!live) {
      for (int k = 0; k < 6; k++) o[k] = 0.0;
      continue;
    }
    double B[49], J[42], X[49], Li[36], y[6];
    for (int k = 0; k < 49; k++) B[k] = mass[49 * i + k];
    for (int r = 0; r < 6; r++)
      for (int c = 0; c < 7; c++) J[7 * r + c] = jac[i * s0 + r * s1 + c * s2];
    if (!cholesky(B, 7)) goto nan;
    /* X's columns: B⁻¹ Jᵀ (6) and B⁻¹ τ, stored as rows of 7 */
    for (int r = 0; r < 6; r++) {
      for (int c = 0; c < 7; c++) X[7 * r + c] = J[7 * r + c];
      cho_solve(B, 7, X + 7 * r);
    }
    for (int c = 0; c < 7; c++) X[42 + c] = t[c];
    cho_solve(B, 7, X + 42);
    for (int r = 0; r < 6; r++) {
      for (int c = 0; c < 6; c++) {
        double s = 0.0;
        for (int k = 0; k < 7; k++) s += J[7 * r + k] * X[7 * c + k];
        Li[6 * r + c] = s + (r == c ? damping : 0.0);
      }
      double s = 0.0;
      for (int k = 0; k < 7; k++) s += J[7 * r + k] * X[42 + k];
      y[r] = s;
    }
    if (!cholesky(Li, 6)) goto nan;
    cho_solve(Li, 6, y);
    for (int k = 0; k < 6; k++) o[k] = y[k];
    continue;
  nan:
    for (int k = 0; k < 6; k++) o[k] = NAN;
  }
}
