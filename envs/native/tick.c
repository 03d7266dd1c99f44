/* PandaEnv's 1-kHz control period in one call (envs/native/tick.py binds it; PandaEnv._tick is the reference).

   `tick_run` composes the package's other C pieces in the order of PandaEnv._tick: mj_step1, the sensing read-out
   (sense.c), f_ext = Λ J B⁻¹ τ_ext (sense.c), the F/T moment at the tool tip and f_ope (period.c), the divergence
   and joint-limit checks (period.c), the controller's QP assembly (a3cqp_step.c), the QP (gi_qp.c), the torque law
   (a3cqp_step.c), the operator's hand and its push (hand.c), and mj_step2. Each piece is called through the
   pointer tick.py takes from its own library, with the arguments the Python period passes it, so every number is
   the one the Python period computes, bit for bit (tests/test_tick_native.py).

   Why C: with the pieces in C, a period at 65 arms is still ~0.5 ms of Python around them (~100 calls that pack,
   check and route arrays), ~20 % of a peg-in-hole evaluation.

   It stops before the controller, with nothing of the controller's state changed, where the Python period takes
   another route: an input that is not finite (the controller's stand-ins), or a QP that is not solved cleanly
   (a status other than solved, handed on to the torch route, or a non-finite x: the fallback brake). tick.py then
   runs the rest of the period in Python, which solves the same QP from the same warm start.

   No MuJoCo headers: mj_step1 and mj_step2 come as pointers from the loaded libmujoco, and the few mjData fields read
   here (ncon, the contact array) by offsets tick.py finds once per process.

   An engine error inside the call (mju_error: MuJoCo's stack exhausted, a user's mjcb_* callback that raised) comes
   back as TICK_ENGINE_ERROR, as the bindings do it (python/mujoco/errors.h): a thread-local error handler installed
   for the call longjmps back here. tick.py then raises mujoco.FatalError with MuJoCo's message, or the callback's
   own Python exception. Without it MuJoCo's default handler prints the message and exits the process. */
#include <math.h>
#include <setjmp.h>
#include <stdio.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

typedef void (*mj_step_fn)(const void* m, void* d);
typedef void (*observe_fn)(const void* args);
typedef void (*wrench_fn)(int64_t n, const double* tau, const double* jac, int64_t s0, int64_t s1, int64_t s2,
                          const double* mass, double damping, double* out);
typedef void (*measure_fn)(const void* a, const double* pos, const double* rot, double* ft, double* truth,
                           const double* f_ext, double* f_ope, double* r_handle, double* handle_pos);
typedef int64_t (*checks_fn)(const void* a, const double* q, const double* qd, const double* pen, double* pen_max,
                             const uint8_t* skip, const uint8_t* live, double* excess, int64_t* joint, double* speed,
                             uint8_t* bad);
typedef void (*assemble_fn)(int64_t n, const void* p, const double* in, double* out);
typedef void (*assemble_robots_fn)(int64_t n, const void* p, const double* in, const double* robot, double* out);
typedef int (*solve_fn)(int64_t B, int64_t n, int64_t p, int64_t m, const double* P, const double* q, const double* A,
                        const double* b, const double* G, const double* h, const double* lb, const double* ub,
                        const double* z0, const int64_t* stride, double tol, int64_t max_steps, double* out);
typedef void (*torque_fn)(int64_t n, const void* p, const double* in, const double* asm_out, const double* x,
                          const uint8_t* ok, const double* leak_extra, double* out);
typedef void (*hand_fn)(const void* a, int64_t k, const double* t, double t_add, const double* pos,
                        const double* twist, const double* r, const double* rot, const double* noise,
                        int64_t noise_stride, double* force, double* torque);
typedef int64_t (*push_fn)(const void* a, const double* force, const double* torque);

/* MuJoCo's error routing (private entry points the bindings use): from 4.0 a thread-local log handler that gets an
   mjLogMessage, before 4.0 a thread-local error function that gets the text */
typedef struct {
  int level, topic; /* mjtLogLevel (3: mjLOG_ERROR), mjtLogTopic */
  char subject[1024];
  const char *body, *func;
} log_message; /* the head of mjLogMessage (mjtype.h) */
typedef void (*log_fn)(const log_message* msg);
typedef log_fn (*set_log_fn)(log_fn handler);
typedef log_fn (*get_log_fn)(void);
typedef void (*error_fn)(const char* msg);
typedef void (*set_error_fn)(error_fn handler);

enum { TICK_DONE = 0, TICK_BEFORE_CONTROLLER = 1, TICK_ENGINE_ERROR = 2 };
enum { IN_FIELDS = 18 };

typedef struct {
  int64_t n, rows; /* arms; the QP's inequality rows m */
  /* the pieces and their argument blocks */
  mj_step_fn step1, step2;
  observe_fn observe;
  wrench_fn wrench;
  measure_fn measure;
  checks_fn checks;
  assemble_fn assemble;
  assemble_robots_fn assemble_robots;
  solve_fn solve;
  torque_fn torque;
  hand_fn hand;
  push_fn push;
  const void *model, *sense_args, *period_args, *params, *hand_args, *push_args;
  void* data;
  /* mjData: the byte offsets of ncon and of the contact pointer; a contact's size and its dist and geom[2] */
  int64_t ncon_offset, contact_offset, contact_size, dist_offset, geom_offset;
  /* MuJoCo's arrays: xfrc_applied [nxfrc], ctrl, qfrc_constraint, qfrc_applied */
  int64_t nxfrc;
  double *xfrc_applied, *ctrl;
  const double *qfrc_constraint, *qfrc_applied;
  const int64_t *act, *dadr, *geom_arm; /* [n, 7], [n, 7], [ngeom] (−1: no arm) */
  /* the sim's read-out (sense.c) and its step's τ_ext, push torques */
  const double *q, *qd, *bias, *mass, *f_env, *cs_pos, *cs_rot, *jt, *twist, *jdot_qdot;
  double *tau_ext, *tau_push;
  /* this period's sensing, written here (the env's attributes after tick.py publishes them) */
  double *pos, *rot, *f_ext, *ft, *f_ope, *r_handle, *handle_pos;
  double* f_sum; /* [2, n, 6] sums of f_env and f_ope over the agent period, or NULL */
  double contact_threshold;
  /* the checks: penetration [n] of this period, its maximum [n] over the agent period; arms skipped and live;
     the joint-limit records; the codes of the arms newly diverged */
  double *pen, *pen_max;
  const uint8_t *skip, *live;
  double *excess, *speed;
  int64_t* joint;
  uint8_t* bad;
  /* the controller: its inputs of the agent period, q*, q̇* [n, 7] (read and written), the packed rows, the
     assembly, the QP's warm start (the last solution: read and written) and scratch, the torque law's output */
  const double *weights, *f_d, *pos_d, *rot_d, *f_ext_limits, *robot_rows, *leak_extra, *tau_max;
  const int64_t* in_offsets; /* [IN_FIELDS] the packed row's fields (a3cqp_step.c's input table order) */
  int64_t in_size;
  double *q_des, *qd_des, *packed, *asm_out, *warm, *qp_out, *tout, *tau;
  const int64_t* strides;
  double tol;
  int64_t max_steps, cold;
  const uint8_t* idle;      /* [n] arms held (τ = h + g, q*, q̇* kept), or NULL */
  int64_t* saturated;       /* [n] periods with a saturated torque (a population's count), or NULL */
  uint8_t* ok;              /* [n] scratch, all 1 */
  /* the hand: the arms' time [n] (s), the tremor draws and their stride, the wrench at the handle [n, 3] */
  const double* t;
  const double* noise;
  int64_t noise_stride;
  double *handle_force, *handle_torque;
  double dt; /* the control period (s) */
  /* A3CQPController's subset of active arms (`SUBSET_MIN_IDLE`): their indices [nsub] (NULL: every arm computed),
     and scratch for their warm start [nsub, m + 26] and leak rates [nsub, 6] */
  const int64_t* sub;
  int64_t nsub;
  double *z0_sub, *leak_sub;
  /* MuJoCo's error routing: the log-handler setter and the global handler's getter (4.0 on), or the error-function
     setter (before 4.0); NULL where absent */
  set_log_fn set_log;
  get_log_fn global_log;
  set_error_fn set_error;
} tick_args;

int64_t tick_args_size(void) { return (int64_t)sizeof(tick_args); }

static _Thread_local jmp_buf engine_jump;
static _Thread_local char engine_message[2048];
static _Thread_local log_fn engine_forward; /* where warnings and info go on (the handler in place before the call) */

/* The message of the last TICK_ENGINE_ERROR on this thread ("function: text", as the bindings word it). */
const char* tick_error_message(void) { return engine_message; }

static void on_log(const log_message* msg) {
  if (msg->level != 3) {
    if (engine_forward) engine_forward(msg);
    return;
  }
  if (msg->func)
    snprintf(engine_message, sizeof engine_message, "%s: %s", msg->func, msg->subject);
  else
    snprintf(engine_message, sizeof engine_message, "%s", msg->subject);
  longjmp(engine_jump, 1);
}

static void on_error(const char* msg) {
  snprintf(engine_message, sizeof engine_message, "%s", msg);
  longjmp(engine_jump, 1);
}

/* PandaSim.max_penetration: the deepest penetration of each arm's contacts (m, 0 without), numpy's maximum (NaN wins) */
static void max_penetration(const tick_args* a) {
  const char* d = (const char*)a->data;
  int32_t ncon = *(const int32_t*)(d + a->ncon_offset);
  const char* con = *(const char* const*)(d + a->contact_offset);
  for (int64_t i = 0; i < a->n; i++) a->pen[i] = 0.0;
  for (int32_t c = 0; c < ncon; c++) {
    const char* e = con + c * a->contact_size;
    const int32_t* g = (const int32_t*)(e + a->geom_offset);
    int64_t arm1 = a->geom_arm[g[0]], arm2 = a->geom_arm[g[1]];
    int64_t arm = arm1 > arm2 ? arm1 : arm2;
    if (arm < 0) continue;
    double v = -*(const double*)(e + a->dist_offset), old = a->pen[arm];
    a->pen[arm] = (old != old || v != v) ? (old != old ? old : v) : (v > old ? v : old);
  }
}

static int all_finite(const double* x, int64_t count) {
  for (int64_t i = 0; i < count; i++)
    if (!isfinite(x[i])) return 0;
  return 1;
}

/* A3CQPController._prepare's check of every arm's q, qd, mass, bias, weights, f_d, pos_d, rot_d, f_ext (a
   non-finite one sends the whole batch to the controller's stand-ins) */
static int inputs_finite(const tick_args* a) {
  for (int64_t i = 0; i < a->n; i++)
    if (!(all_finite(a->q + 7 * i, 7) && all_finite(a->qd + 7 * i, 7) && all_finite(a->mass + 49 * i, 49) &&
          all_finite(a->bias + 7 * i, 7) && all_finite(a->weights + 18 * i, 18) && all_finite(a->f_d + 6 * i, 6) &&
          all_finite(a->pos_d + 3 * i, 3) && all_finite(a->rot_d + 9 * i, 9) && all_finite(a->f_ext + 6 * i, 6)))
      return 0;
  return 1;
}

/* arm i's packed input row (a3cqp_step.c's table: q, qd, mass, bias, jac, jdot_qdot, twist, pos, rot, weights, f_d,
   pos_d, rot_d, f_ext, in_contact, q_des, qd_des, f_ext_limits) */
static void pack(const tick_args* a, int64_t i, double* row) {
  const int64_t* o = a->in_offsets;
  const double thr2 = a->contact_threshold * a->contact_threshold;
  memcpy(row + o[0], a->q + 7 * i, 7 * sizeof(double));
  memcpy(row + o[1], a->qd + 7 * i, 7 * sizeof(double));
  memcpy(row + o[2], a->mass + 49 * i, 49 * sizeof(double));
  memcpy(row + o[3], a->bias + 7 * i, 7 * sizeof(double));
  const double* jt = a->jt + 84 * i; /* [Jᵀ | J̇ᵀ] 7 × 12 */
  for (int r = 0; r < 6; r++)
    for (int c = 0; c < 7; c++) row[o[4] + 7 * r + c] = jt[12 * c + r];
  memcpy(row + o[5], a->jdot_qdot + 6 * i, 6 * sizeof(double));
  memcpy(row + o[6], a->twist + 6 * i, 6 * sizeof(double));
  memcpy(row + o[7], a->cs_pos + 3 * i, 3 * sizeof(double));
  memcpy(row + o[8], a->cs_rot + 9 * i, 9 * sizeof(double));
  memcpy(row + o[9], a->weights + 18 * i, 18 * sizeof(double));
  memcpy(row + o[10], a->f_d + 6 * i, 6 * sizeof(double));
  memcpy(row + o[11], a->pos_d + 3 * i, 3 * sizeof(double));
  memcpy(row + o[12], a->rot_d + 9 * i, 9 * sizeof(double));
  memcpy(row + o[13], a->f_ext + 6 * i, 6 * sizeof(double));
  const double* f = a->ft + 6 * i;
  row[o[14]] = (f[0] * f[0] + f[1] * f[1]) + f[2] * f[2] > thr2 ? 1.0 : 0.0;
  memcpy(row + o[15], a->q_des + 7 * i, 7 * sizeof(double));
  memcpy(row + o[16], a->qd_des + 7 * i, 7 * sizeof(double));
  row[o[17]] = a->f_ext_limits[i];
}

/* The controller's step (A3CQPController._step_native) of the arms computed (every arm, or the subset `sub`): 0
   where its Python takes another route (nothing of its state changed then). */
static int control(const tick_args* a) {
  const int64_t n = a->n, m = a->rows, NV = 13, nd = m + 2 * NV;
  const int64_t nr = a->sub ? a->nsub : n;
  if (!inputs_finite(a)) return 0;
  for (int64_t j = 0; j < nr; j++) pack(a, a->sub ? a->sub[j] : j, a->packed + a->in_size * j);
  if (a->robot_rows)
    a->assemble_robots(nr, a->params, a->packed, a->robot_rows, a->asm_out);
  else
    a->assemble(nr, a->params, a->packed, a->asm_out);
  const double *P = a->asm_out, *c = P + NV * NV * nr, *G = c + NV * nr, *h = G + m * NV * nr;
  /* the warm start: the last solution's multipliers (QPSolution.take of the subset's) */
  const double* z0 = NULL;
  const double* leak = a->leak_extra;
  if (!a->cold) z0 = a->warm + NV * n;
  if (a->sub) {
    if (!a->cold) {
      for (int64_t j = 0; j < nr; j++) memcpy(a->z0_sub + nd * j, z0 + nd * a->sub[j], (size_t)nd * sizeof(double));
      z0 = a->z0_sub;
    }
    if (leak) {
      for (int64_t j = 0; j < nr; j++) memcpy(a->leak_sub + 6 * j, leak + 6 * a->sub[j], 6 * sizeof(double));
      leak = a->leak_sub;
    }
  }
  if (a->solve(nr, NV, 0, m, P, c, NULL, NULL, G, h, NULL, NULL, z0, a->strides, a->tol, a->max_steps, a->qp_out))
    return 0;
  if (!all_finite(a->qp_out, NV * nr)) return 0;
  a->torque(nr, a->params, a->packed, a->asm_out, a->qp_out, a->ok, leak, a->tout);
  /* the solution is the next warm start (QPSolution.put of the subset's: x, multipliers, status, solves) */
  if (a->sub) {
    if (a->cold) memset(a->warm, 0, (size_t)(n * (NV + nd + 2)) * sizeof(double));
    const double* x = a->qp_out;
    for (int64_t j = 0; j < nr; j++) {
      int64_t i = a->sub[j];
      memcpy(a->warm + NV * i, x + NV * j, (size_t)NV * sizeof(double));
      memcpy(a->warm + NV * n + nd * i, x + NV * nr + nd * j, (size_t)nd * sizeof(double));
      a->warm[n * (NV + nd) + i] = x[nr * (NV + nd) + j];
      a->warm[n * (NV + nd + 1) + i] = x[nr * (NV + nd + 1) + j];
    }
  } else {
    memcpy(a->warm, a->qp_out, (size_t)(n * (NV + nd + 2)) * sizeof(double));
  }
  /* the arms held keep their q*, q̇* and get h + g (clipped) */
  for (int64_t i = 0; i < n; i++) {
    if (!a->idle || !a->idle[i]) continue;
    for (int j = 0; j < 7; j++) {
      double b = a->bias[7 * i + j], lim = a->tau_max[j];
      a->tau[7 * i + j] = b < -lim ? -lim : (b > lim ? lim : b);
    }
  }
  const double *tau = a->tout, *qs = a->tout + 27 * nr, *qds = a->tout + 34 * nr, *sat = a->tout + 41 * nr;
  for (int64_t j = 0; j < nr; j++) {
    int64_t i = a->sub ? a->sub[j] : j;
    if (a->idle && a->idle[i]) continue;
    memcpy(a->tau + 7 * i, tau + 7 * j, 7 * sizeof(double));
    memcpy(a->q_des + 7 * i, qs + 7 * j, 7 * sizeof(double));
    memcpy(a->qd_des + 7 * i, qds + 7 * j, 7 * sizeof(double));
    if (a->saturated && sat[j] != 0.0) a->saturated[i] += 1;
  }
  return 1;
}

static int64_t period(const tick_args* a, int64_t k, int64_t hand_k, int64_t pushed, int64_t* flags) {
  const int64_t n = a->n;
  *flags = 0;
  /* PandaSim._observe_arrays: a push lasts one step */
  if (pushed) {
    memset(a->xfrc_applied, 0, (size_t)a->nxfrc * sizeof(double));
    memset(a->tau_push, 0, (size_t)(7 * n) * sizeof(double));
  }
  a->step1(a->model, a->data);
  a->observe(a->sense_args);
  /* PandaEnv._measure with ideal sensors */
  memcpy(a->pos, a->cs_pos, (size_t)(3 * n) * sizeof(double));
  memcpy(a->rot, a->cs_rot, (size_t)(9 * n) * sizeof(double));
  memcpy(a->ft, a->f_env, (size_t)(6 * n) * sizeof(double));
  a->wrench(n, a->tau_ext, a->jt, 84, 1, 12, a->mass, 1e-6, a->f_ext); /* J = [Jᵀ | J̇ᵀ][:, :, :6]ᵀ */
  a->measure(a->period_args, a->pos, a->rot, a->ft, NULL, a->f_ext, a->f_ope, a->r_handle, a->handle_pos);
  if (a->f_sum) {
    for (int64_t j = 0; j < 6 * n; j++) a->f_sum[j] += a->ft[j];
    for (int64_t j = 0; j < 6 * n; j++) a->f_sum[6 * n + j] += a->f_ope[j];
  }
  max_penetration(a);
  if (a->checks(a->period_args, a->q, a->qd, a->pen, a->pen_max, a->skip, a->live, a->excess, a->joint, a->speed,
                a->bad))
    *flags |= 1;
  if (!control(a)) return TICK_BEFORE_CONTROLLER;
  /* the operator's hand at the handle, pushed (NativeHand) */
  a->hand(a->hand_args, hand_k, a->t, (double)k * a->dt, a->handle_pos, a->twist, a->r_handle, a->rot,
          a->noise ? a->noise + 3 * k : NULL, a->noise_stride, a->handle_force, a->handle_torque);
  int64_t push = a->push(a->push_args, a->handle_force, a->handle_torque);
  if (push) *flags |= 2;
  /* PandaSim.step */
  for (int64_t j = 0; j < 7 * n; j++) a->ctrl[a->act[j]] = a->tau[j];
  a->step2(a->model, a->data);
  for (int64_t i = 0; i < n; i++)
    for (int j = 0; j < 7; j++) {
      int64_t dof = a->dadr[7 * i + j];
      a->tau_ext[7 * i + j] = a->qfrc_constraint[dof] + a->qfrc_applied[dof];
    }
  if (push)
    for (int64_t j = 0; j < 7 * n; j++) a->tau_ext[j] += a->tau_push[j];
  return TICK_DONE;
}

/* One control period of every arm (the k-th of the agent period; `hand_k`: the operator's history slot; `pushed`:
   whether the last period pushed). Returns TICK_DONE, TICK_BEFORE_CONTROLLER where the rest of the period is
   Python's (the sensing and the checks done, the controller's state unchanged), or TICK_ENGINE_ERROR (MuJoCo's
   message in tick_error_message; the period left where the error stopped it, as after the bindings' FatalError).
   `*flags`: bit 0 some arm newly diverged (`bad`), bit 1 the hand pushes this period. */
int64_t tick_run(const tick_args* a, int64_t k, int64_t hand_k, int64_t pushed, int64_t* flags) {
  log_fn previous = NULL;
  if (a->set_log) {
    previous = a->set_log(on_log);
    engine_forward = previous ? previous : a->global_log();
  } else if (a->set_error) {
    a->set_error(on_error);
  }
  int64_t result;
  if (setjmp(engine_jump) == 0)
    result = period(a, k, hand_k, pushed, flags);
  else
    result = TICK_ENGINE_ERROR;
  if (a->set_log)
    a->set_log(previous);
  else if (a->set_error)
    a->set_error(NULL);
  return result;
}
