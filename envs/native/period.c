/* PandaEnv's arithmetic of a 1-kHz control period around the read-out, in two calls (envs/native/period.py binds
   them).

   `period_measure` is the tail of PandaEnv._measure: the F/T reading's moment moved from the sensor's site to the
   tool tip (τ_tip = τ_site + (p_site − p_tip) × F), f_ope = f_ext − f_env, and the handle's position.
   `period_checks` is PandaEnv._check_divergence and _track_joint_limits: which arms diverged (non-finite state, a
   joint faster than a factor times its limit, a contact too deep), and each live arm's worst joint-limit excess and
   joint-speed ratio of its episode.

   Why C: at 65 arms the numpy form is ~30 numpy calls per control period (~120 µs of ~2.2 ms) for ~100 flops and
   comparisons per arm. The comparisons are the same; the products are summed in another order than numpy's, so the
   wrenches agree with the numpy path to round-off (tests/test_period_native.py); the numpy path stays the reference. */
#include <math.h>
#include <stdint.h>

typedef struct {
  int64_t n;
  double speed_factor;  /* panda.divergence_speed_factor */
  double penetration;   /* panda.divergence_penetration (m) */
  const double* dq_max; /* [7] rad/s (datasheet) */
  const double* q_lo;   /* [7] rad */
  const double* q_hi;
  const double* o_ft;     /* [3] the F/T site from the tool tip, tool frame (m) */
  const double* o_handle; /* [3] the handle from the tool tip, tool frame (m) */
} period_args;

static void cross(const double* a, const double* b, double* out) {
  out[0] = a[1] * b[2] - a[2] * b[1];
  out[1] = a[2] * b[0] - a[0] * b[2];
  out[2] = a[0] * b[1] - a[1] * b[0];
}

static void rotate(const double* R, const double* v, double* out) {
  for (int k = 0; k < 3; k++) out[k] = R[3 * k] * v[0] + R[3 * k + 1] * v[1] + R[3 * k + 2] * v[2];
}

/* ft [n, 6] (world; moment about the F/T site) and, when not NULL, `truth` (the same without sensor errors):
   moments moved to the tool tip, in place; f_ope = f_ext − ft; r_handle [n, 3] = R o_handle; handle_pos = pos +
   r_handle (rot [n, 3, 3], pos [n, 3]: the tool tip's pose). */
void period_measure(const period_args* a, const double* pos, const double* rot, double* ft, double* truth,
                    const double* f_ext, double* f_ope, double* r_handle, double* handle_pos) {
  for (int64_t i = 0; i < a->n; i++) {
    const double* R = rot + 9 * i;
    double lever[3], m[3];
    rotate(R, a->o_ft, lever);
    double* f = ft + 6 * i;
    cross(lever, f, m);
    for (int k = 0; k < 3; k++) f[3 + k] += m[k];
    if (truth) {
      double* g = truth + 6 * i;
      cross(lever, g, m);
      for (int k = 0; k < 3; k++) g[3 + k] += m[k];
    }
    for (int k = 0; k < 6; k++) f_ope[6 * i + k] = f_ext[6 * i + k] - f[k];
    rotate(R, a->o_handle, r_handle + 3 * i);
    for (int k = 0; k < 3; k++) handle_pos[3 * i + k] = pos[3 * i + k] + r_handle[3 * i + k];
  }
}

/* bad [n]: 0, or why the arm newly diverged (1 non-finite state, 2 joint speed beyond the factor, 3 contact deeper
   than the bound; arms `skip` [n] not checked: diverged or parked), from q, qd [n, 7] and the deepest penetration
   pen [n] (m), whose maximum `pen_max` [n] keeps. For arms `live` [n]: `excess` [n] (rad) and its joint `joint`
   [n] keep the worst excess past a position limit, `speed` [n] the worst |q̇| / q̇_max. Returns the arms bad. */
int64_t period_checks(const period_args* a, const double* q, const double* qd, const double* pen, double* pen_max,
                      const uint8_t* skip, const uint8_t* live, double* excess, int64_t* joint, double* speed,
                      uint8_t* bad) {
  int64_t count = 0;
  for (int64_t i = 0; i < a->n; i++) {
    const double* qi = q + 7 * i;
    const double* vi = qd + 7 * i;
    int finite = 1, fast = 0, nan_q = 0, nan_v = 0;
    double over = 0.0, ratio = 0.0;
    int64_t worst = 0;
    for (int j = 0; j < 7; j++) {
      double v = fabs(vi[j]);
      finite &= isfinite(qi[j]) && isfinite(vi[j]);
      fast |= v > a->speed_factor * a->dq_max[j]; /* (a NaN compares false) */
      nan_q |= isnan(qi[j]);
      nan_v |= isnan(vi[j]);
      double lo = a->q_lo[j] - qi[j], hi = qi[j] - a->q_hi[j];
      double e = lo > hi ? lo : hi;
      double r = v / a->dq_max[j];
      if (j == 0 || e > over) { /* argmax: the first of equal maxima */
        over = e;
        worst = j;
      }
      if (j == 0 || r > ratio) ratio = r;
    }
    if (pen[i] > pen_max[i] || isnan(pen[i])) pen_max[i] = pen[i];
    uint8_t why = 0;
    if (!skip[i]) why = !finite ? 1 : (fast ? 2 : (pen[i] > a->penetration ? 3 : 0));
    bad[i] = why;
    count += why != 0;
    if (live[i]) { /* (numpy's maximum over a row with a NaN is NaN, which compares false: the records stay) */
      if (!nan_q && over > excess[i]) {
        excess[i] = over;
        joint[i] = worst;
      }
      if (!nan_v && ratio > speed[i]) speed[i] = ratio;
    }
  }
  return count;
}

int64_t period_args_size(void) { return (int64_t)sizeof(period_args); }
