/* One A2C iteration on the point-mass surrogate, in C: n agent steps of N envs + one update.
 *
 * A translation of the torch reference, function by function, in the same order of operations (the point mass
 * itself, envs/point_mass.py's agent_step, observe_state and auto_reset, comes from envs/native/point_mass.h):
 *   algorithms/a2c.py    rollout_step, nstep_returns / gae_advantages, a2c_update (eq. 31, hand-derived gradients)
 *   algorithms/networks.py  _stack_forward, forward, backward (tanh MLPs in one flat float32 vector)
 *   algorithms/rmsprop.py   clip_grad_norm_ (λζ), rmsprop_step_ (eq. 32)
 * Physics in double, networks in float, as the reference.  algorithms/native/__init__.py fills `a2c_params`
 * and the pointer table; tests/test_a2c_native.py checks this file against the torch code.
 *
 * Dot products use `omp simd` reductions (-fopenmp-simd, no OpenMP runtime): vectorised, in a fixed order, so
 * the same binary gives the same numbers (not bit-equal to MKL's, which sums in its own order).  -fno-math-errno
 * lets sqrtf vectorise (it only drops errno; IEEE results are unchanged).
 */
#include <math.h>
#include <stdint.h>
#include <string.h>

#include "point_mass.h" /* envs/native: the eq. 35 step, observation and auto-reset */

#define MAX_DEPTH 8
#define LOG_2PI 1.8378770664093453

typedef struct {
    pm_params env; /* the point mass: N envs, episode_steps, substeps, sched_len, physics, adaptation, reward */
    /* sizes */
    int64_t n;
    int64_t obs_dim, act_dim, critic_dim, privileged, shared, depth, hidden[MAX_DEPTH], size;
    /* flat-vector offsets: stack 0 = pi (or trunk), stack 1 = vf (separate only) */
    int64_t off_w[2][MAX_DEPTH], off_b[2][MAX_DEPTH], off_pi_w, off_pi_b, off_vf_w, off_vf_b, off_log_std;
    int64_t in_dim[2];
    int64_t gae, normalize_advantage;
    double gamma, gae_lambda, vf_coef, ent_coef, bound_coef, max_grad_norm, lr, rms_alpha, rms_eps;
} a2c_params;

/* The pointer table, in this order (Python: STATE, PENDING and the rest, algorithms/native/__init__.py). */
enum {
    B_X, B_XD, B_TARGET, B_WLOG, B_FD, B_WALL, B_HASWALL, B_T, B_FENV, B_FOPE, B_SCEN, B_SLOT,
    B_P_TARGET, B_P_WALL, B_P_HASWALL, B_P_SCEN, B_P_WLOG, B_P_FD,
    B_SCHED, B_NOISE, B_FLAT, B_SQ, B_METRICS, B_REWARDS, B_DONES, B_WORK, B_COUNT
};

int64_t a2c_params_size(void) { return (int64_t)sizeof(a2c_params); }
int64_t a2c_buffer_count(void) { return B_COUNT; }

static int64_t hmax(const a2c_params *P) {
    int64_t m = P->act_dim;
    for (int64_t l = 0; l < P->depth; l++) m = P->hidden[l] > m ? P->hidden[l] : m;
    return m;
}

static int64_t acts_floats(const a2c_params *P, int64_t rows) {
    int64_t s = 0;
    for (int64_t l = 0; l < P->depth; l++) s += rows * P->hidden[l];
    return s;
}

/* float32 workspace entries this iteration needs */
int64_t a2c_workspace_floats(const a2c_params *P) {
    int64_t B = P->n * P->env.N, D = P->critic_dim, A = P->act_dim, H = hmax(P);
    return 2 * B * D + 2 * B * A      /* obs, final obs; actions, mu */
           + acts_floats(P, B)       /* policy stack at obs (from acting) */
           + acts_floats(P, 2 * B)   /* value stack (or trunk at next_obs) */
           + 2 * B + 3 * B            /* values at [obs; next obs]; adv, returns, V at gathered final obs */
           + P->size                  /* gradient */
           + 2 * B * H + 2 * B * A    /* backward scratch; g_mu */
           + P->size + B * D;         /* transposed weights; gathered final observations */
}

/* ------------------------------------------------------------------ networks (algorithms/networks.py) */

/* exp(z) for z <= 0 and tanh, in plain arithmetic so that row loops vectorise: glibc's tanhf (via expm1f) was
 * ~70 % of an iteration at the paper's size, and a scalar expf call per activation still ~15 %.  Cody-Waite
 * reduction (|r| <= ln2/2) and a degree-6 Taylor polynomial: relative error ~1e-7; tanh's absolute error ~1e-7
 * (cancellation in 1 - t near 0), below float32's resolution of the activations that follow. */
static inline float exp_nonpos(float z) {
    z = z < -87.0f ? -87.0f : z;
    int32_t n = (int32_t)(z * 1.44269504f - 0.5f);  /* round to nearest (z <= 0: truncation is a ceiling) */
    float fn = (float)n, r = (z - fn * 0.693145751953125f) - fn * 1.428606765330187e-06f;
    float p = 1.0f + r * (1.0f + r * (0.5f + r * (0.16666667f + r * (0.041666668f + r * (0.008333334f
                                                                                       + r * 0.0013888889f)))));
    union { int32_t i; float f; } scale = {.i = (n + 127) << 23};  /* 2^n (a union, not memcpy: the loop vectorises) */
    return p * scale.f;
}

/* Four floats in one register (GNU C vector extension, GCC and clang: SSE on x86-64, NEON on arm64, plain scalars
 * elsewhere).  v + s * w is a multiply then an add, each rounded, as the scalar code: the kernels below keep each
 * sum's order of terms, they only hold the partial sums in registers across a whole sum instead of in memory. */
typedef float v4 __attribute__((vector_size(16)));
static inline v4 ld4(const float *p) { v4 v; memcpy(&v, p, sizeof v); return v; }
static inline void st4(float *p, v4 v) { memcpy(p, &v, sizeof v); }
static inline v4 bc4(float s) { return (v4){s, s, s, s}; }
typedef int32_t v4i __attribute__((vector_size(16)));
static inline v4i bc4i(int32_t s) { return (v4i){s, s, s, s}; }
static inline v4 sel4(v4i mask, v4 a, v4 b) { return (v4)(((v4i)a & mask) | ((v4i)b & ~mask)); } /* mask ? a : b */

/* Elementwise loops that run faster on wider registers (RMSProp's square roots and divisions) get an AVX2 copy,
 * chosen at load time (GCC's target_clones, x86-64 Linux): the same IEEE operations lane by lane (no FMA: the C
 * standard mode keeps a * b + c two roundings), so the same numbers on every machine.  Reductions never get one:
 * their order of terms follows the register width. */
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__) && defined(__linux__) && __GNUC__ >= 8
#define ELEMENTWISE_CLONES __attribute__((target_clones("avx2", "default")))
#define ELEMENTWISE_CLONES_512 __attribute__((target_clones("avx512f", "avx2", "default")))
#else
#define ELEMENTWISE_CLONES
#define ELEMENTWISE_CLONES_512
#endif


/* exp_nonpos and tanh_row's arithmetic on eight lanes, operation for operation (GCC does not vectorise the scalar
 * loop: the clamp and the sign are control flow to it) */
typedef float v8 __attribute__((vector_size(32)));
typedef int32_t v8i __attribute__((vector_size(32)));
#define BC8I(s) ((v8i){s, s, s, s, s, s, s, s})
#define BC8(s) ((v8){s, s, s, s, s, s, s, s})
#define SEL8(mask, a, b) ((v8)(((v8i)(a) & (mask)) | ((v8i)(b) & ~(mask))))

ELEMENTWISE_CLONES
static void tanh_row(float *y, int64_t len) {
    int64_t i = 0;
    for (; i + 8 <= len; i += 8) {
        v8 x, z;
        memcpy(&x, y + i, sizeof x);
        v8 a = (v8)((v8i)x & ~BC8I(INT32_MIN));
        z = BC8(-2.0f) * a;
        z = SEL8(z < BC8(-87.0f), BC8(-87.0f), z);
        v8i n = __builtin_convertvector(z * BC8(1.44269504f) - BC8(0.5f), v8i);
        v8 fn = __builtin_convertvector(n, v8);
        v8 r = (z - fn * BC8(0.693145751953125f)) - fn * BC8(1.428606765330187e-06f);
        v8 p = BC8(1.0f) + r * (BC8(1.0f) + r * (BC8(0.5f) + r * (BC8(0.16666667f) + r * (BC8(0.041666668f)
                                                    + r * (BC8(0.008333334f) + r * BC8(0.0013888889f))))));
        v8 t = p * (v8)((n + BC8I(127)) << 23);
        v8 v = (BC8(1.0f) - t) / (BC8(1.0f) + t);
        v = SEL8(x < BC8(0.0f), -v, v);
        memcpy(y + i, &v, sizeof v);
    }
    for (; i < len; i++) {
        float a = fabsf(y[i]), t = exp_nonpos(-2.0f * a), v = (1.0f - t) / (1.0f + t);
        y[i] = y[i] < 0.0f ? -v : v;
    }
}

/* y[r, o] = bias[o] + x[r, :] . W[o, :]  (addmm(b, x, W.T)): the linear heads */
static void linear(const float *x, int64_t rows, int64_t in, int64_t ldx, const float *W, const float *b,
                   int64_t out, float *y) {
    for (int64_t r = 0; r < rows; r++) {
        const float *xr = x + r * ldx;
        for (int64_t o = 0; o < out; o++) {
            const float *wo = W + o * in;
            float acc = 0.0f;
#pragma omp simd reduction(+ : acc)
            for (int64_t k = 0; k < in; k++) acc += xr[k] * wo[k];
            y[r * out + o] = acc + b[o];
        }
    }
}

/* y[r, c] = ((init[c] + x[r,0] M[0,c]) + x[r,1] M[1,c]) + ..., the n terms in order (init NULL: from 0), for x
 * [rows, n] (row stride ldx) and M [n, cols] row-major.  Four rows by eight columns at a time, the 32 partial sums
 * in registers over k; the same operations in the same order on every path (no FMA: -ffp-contract=off) */
ELEMENTWISE_CLONES
static void rows_times(const float *x, int64_t rows, int64_t n, int64_t ldx, const float *M, int64_t cols,
                       const float *init, float *y) {
    float zeros[8] = {0};
    int64_t r = 0;
    for (; r + 4 <= rows; r += 4) {
        const float *x0 = x + r * ldx, *x1 = x0 + ldx, *x2 = x1 + ldx, *x3 = x2 + ldx;
        float *y0 = y + r * cols, *y1 = y0 + cols, *y2 = y1 + cols, *y3 = y2 + cols;
        int64_t c = 0;
        for (; c + 8 <= cols; c += 8) {
            const float *i0 = init ? init + c : zeros;
            v4 b0 = ld4(i0), b1 = ld4(i0 + 4);
            v4 a00 = b0, a01 = b1, a10 = b0, a11 = b1, a20 = b0, a21 = b1, a30 = b0, a31 = b1;
            for (int64_t k = 0; k < n; k++) {
                const float *mk = M + k * cols + c;
                v4 w0 = ld4(mk), w1 = ld4(mk + 4), s;
                s = bc4(x0[k]); a00 += s * w0; a01 += s * w1;
                s = bc4(x1[k]); a10 += s * w0; a11 += s * w1;
                s = bc4(x2[k]); a20 += s * w0; a21 += s * w1;
                s = bc4(x3[k]); a30 += s * w0; a31 += s * w1;
            }
            st4(y0 + c, a00); st4(y0 + c + 4, a01); st4(y1 + c, a10); st4(y1 + c + 4, a11);
            st4(y2 + c, a20); st4(y2 + c + 4, a21); st4(y3 + c, a30); st4(y3 + c + 4, a31);
        }
        for (; c < cols; c++) {
            float i0 = init ? init[c] : 0.0f;
            float a0 = i0, a1 = i0, a2 = i0, a3 = i0;
            for (int64_t k = 0; k < n; k++) {
                float w = M[k * cols + c];
                a0 += x0[k] * w; a1 += x1[k] * w; a2 += x2[k] * w; a3 += x3[k] * w;
            }
            y0[c] = a0; y1[c] = a1; y2[c] = a2; y3[c] = a3;
        }
    }
    for (; r < rows; r++) {
        const float *xr = x + r * ldx;
        float *yr = y + r * cols;
        int64_t c = 0;
        for (; c + 8 <= cols; c += 8) {
            const float *i0 = init ? init + c : zeros;
            v4 a0 = ld4(i0), a1 = ld4(i0 + 4);
            for (int64_t k = 0; k < n; k++) {
                v4 s = bc4(xr[k]);
                a0 += s * ld4(M + k * cols + c); a1 += s * ld4(M + k * cols + c + 4);
            }
            st4(yr + c, a0); st4(yr + c + 4, a1);
        }
        for (; c < cols; c++) {
            float a = init ? init[c] : 0.0f;
            for (int64_t k = 0; k < n; k++) a += xr[k] * M[k * cols + c];
            yr[c] = a;
        }
    }
}

/* the same as `linear` with W^T [in, out] (`transpose`), then tanh: y[r, o] = ((b[o] + x[r,0] W[o,0]) + x[r,1]
 * W[o,1]) + ..., the terms in input order (the hidden layers; `linear` is kept for 1-4 outputs) */
static void linear_t(const float *x, int64_t rows, int64_t in, int64_t ldx, const float *Wt, const float *b,
                     int64_t out, float *y) {
    rows_times(x, rows, in, ldx, Wt, out, b, y);
    tanh_row(y, rows * out);
}

#if defined(__clang__) || __GNUC__ >= 12
#define SHUFFLE4(a, b, i, j, k, l) __builtin_shufflevector(a, b, i, j, k, l)
#else
#define SHUFFLE4(a, b, i, j, k, l) __builtin_shuffle(a, b, (v4i){i, j, k, l})
#endif

/* Wt [in, out] = W^T: 4 x 4 blocks through registers, the edges one by one */
static void transpose(const float *W, int64_t out, int64_t in, float *Wt) {
    int64_t o = 0;
    for (; o + 4 <= out; o += 4) {
        int64_t k = 0;
        for (; k + 4 <= in; k += 4) {
            v4 r0 = ld4(W + o * in + k), r1 = ld4(W + (o + 1) * in + k), r2 = ld4(W + (o + 2) * in + k),
               r3 = ld4(W + (o + 3) * in + k);
            v4 t0 = SHUFFLE4(r0, r1, 0, 4, 1, 5), t1 = SHUFFLE4(r2, r3, 0, 4, 1, 5);
            v4 t2 = SHUFFLE4(r0, r1, 2, 6, 3, 7), t3 = SHUFFLE4(r2, r3, 2, 6, 3, 7);
            st4(Wt + k * out + o, SHUFFLE4(t0, t1, 0, 1, 4, 5));
            st4(Wt + (k + 1) * out + o, SHUFFLE4(t0, t1, 2, 3, 6, 7));
            st4(Wt + (k + 2) * out + o, SHUFFLE4(t2, t3, 0, 1, 4, 5));
            st4(Wt + (k + 3) * out + o, SHUFFLE4(t2, t3, 2, 3, 6, 7));
        }
        for (; k < in; k++)
            for (int64_t j = o; j < o + 4; j++) Wt[k * out + j] = W[j * in + k];
    }
    for (; o < out; o++)
        for (int64_t k = 0; k < in; k++) Wt[k * out + o] = W[o * in + k];
}

/* _stack_forward of stack `st` over `rows` inputs x (row stride ldx, first in_dim columns), with the hidden weights
 * transposed in `wt` (at the flat offsets).  Layer l's outputs go to the l-th block of `acts`, blocks of `block_rows`
 * rows, from row `row0` on (the rollout writes step t's N rows into the B-row blocks the update reads).  Returns
 * the last layer's outputs. */
static const float *stack_forward(const a2c_params *P, const float *flat, const float *wt, int st, const float *x,
                                  int64_t rows, int64_t ldx, float *acts, int64_t block_rows, int64_t row0) {
    const float *in = x;
    int64_t width = P->in_dim[st], ld = ldx;
    for (int64_t l = 0; l < P->depth; l++) {
        float *out = acts + row0 * P->hidden[l];
        linear_t(in, rows, width, ld, wt + P->off_w[st][l], flat + P->off_b[st][l], P->hidden[l], out);
        in = out; width = P->hidden[l]; ld = width;
        acts += block_rows * P->hidden[l];
    }
    return in;
}

static const float *last_layer(const a2c_params *P, const float *acts, int64_t rows) {
    for (int64_t l = 0; l + 1 < P->depth; l++) acts += rows * P->hidden[l];
    return acts;
}

/* dW[o, k] += sum over rows r (in row order) of g[r, o] inp[r, k]; db[o] likewise: eight k at a time, the sums over
 * the rows in registers */
ELEMENTWISE_CLONES
static void weight_grad(const float *g, int64_t rows, int64_t h, const float *inp, int64_t ld, int64_t in, float *gw,
                        float *gb) {
    for (int64_t o = 0; o < h; o++) {
        float *gwo = gw + o * in;
        int64_t k = 0;
        for (; k + 8 <= in; k += 8) {
            v4 a0 = ld4(gwo + k), a1 = ld4(gwo + k + 4);
            for (int64_t r = 0; r < rows; r++) {
                v4 s = bc4(g[r * h + o]);
                a0 += s * ld4(inp + r * ld + k); a1 += s * ld4(inp + r * ld + k + 4);
            }
            st4(gwo + k, a0); st4(gwo + k + 4, a1);
        }
        for (; k < in; k++) {
            float a = gwo[k];
            for (int64_t r = 0; r < rows; r++) a += g[r * h + o] * inp[r * ld + k];
            gwo[k] = a;
        }
        float a = gb[o];
        for (int64_t r = 0; r < rows; r++) a += g[r * h + o];
        gb[o] = a;
    }
}

/* g_prev[r, k] = sum over o (in order, from 0) of g[r, o] W[o, k] */
static void input_grad(const float *g, int64_t rows, int64_t h, const float *W, int64_t in, float *g_prev) {
    rows_times(g, rows, h, h, W, in, NULL, g_prev);
}

static void stack_backward(const a2c_params *P, const float *flat, int st, const float *x, int64_t ldx,
                           const float *acts, int64_t rows, float *g, float *g_prev, float *grad) {
    const float *layer_out[MAX_DEPTH];
    const float *a = acts;
    for (int64_t l = 0; l < P->depth; l++) { layer_out[l] = a; a += rows * P->hidden[l]; }
    for (int64_t l = P->depth - 1; l >= 0; l--) {
        int64_t h = P->hidden[l], in = l == 0 ? P->in_dim[st] : P->hidden[l - 1];
        const float *y = layer_out[l];
        for (int64_t r = 0; r < rows * h; r++) g[r] *= 1.0f - y[r] * y[r];  /* tanh' = 1 - tanh^2 */
        float *gw = grad + P->off_w[st][l], *gb = grad + P->off_b[st][l];
        const float *inp = l == 0 ? x : layer_out[l - 1];
        int64_t ld = l == 0 ? ldx : in;
        weight_grad(g, rows, h, inp, ld, in, gw, gb);
        if (l > 0) {  /* g_prev = g @ W */
            input_grad(g, rows, h, flat + P->off_w[st][l], in, g_prev);
            float *tmp = g; g = g_prev; g_prev = tmp;
        }
    }
}

/* grad of a linear head out = h W^T + b, given g_out [rows, out]: accumulate dW, db; g_h = g_out W (added into g_h) */
static void head_backward(const float *h, int64_t rows, int64_t in, const float *W, const float *g_out, int64_t out,
                          float *gW, float *gb, float *g_h) {
    for (int64_t r = 0; r < rows; r++) {
        const float *hr = h + r * in;
        for (int64_t o = 0; o < out; o++) {
            float go = g_out[r * out + o];
            float *gwo = gW + o * in;
            const float *wo = W + o * in;
            float *ghr = g_h + r * in;
#pragma omp simd
            for (int64_t k = 0; k < in; k++) { gwo[k] += go * hr[k]; ghr[k] += go * wo[k]; }
            gb[o] += go;
        }
    }
}

/* eq. 32 on the clipped gradient grad * scale */
ELEMENTWISE_CLONES_512
static void rmsprop(float *flat, float *sq, const float *grad, int64_t size, float scale, float al, float lr,
                    float eps) {
#pragma omp simd
    for (int64_t k = 0; k < size; k++) {
        float g = grad[k] * scale;
        sq[k] = sq[k] * al + (1.0f - al) * g * g;
        flat[k] -= lr * g / sqrtf(sq[k] + eps);
    }
}

/* ------------------------------------------------------------------ the iteration */

/* returns the number of episode ends in the rollout */
int64_t a2c_iteration(const a2c_params *P, void **buf) {
    const int64_t N = P->env.N, n = P->n, B = n * N, D = P->critic_dim, A = P->act_dim;
    const int64_t H = hmax(P), hl = P->hidden[P->depth - 1];
    pm_state s = {buf[B_X], buf[B_XD], buf[B_TARGET], buf[B_WLOG], buf[B_FD], buf[B_WALL], buf[B_FENV], buf[B_FOPE],
                    buf[B_HASWALL], buf[B_T], buf[B_SCEN], buf[B_SLOT]};
    pm_state p = {NULL, NULL, buf[B_P_TARGET], buf[B_P_WLOG], buf[B_P_FD], buf[B_P_WALL], NULL, NULL,
                    buf[B_P_HASWALL], NULL, buf[B_P_SCEN], NULL};
    const double *sched = buf[B_SCHED];
    const float *noise = buf[B_NOISE];
    float *flat = buf[B_FLAT], *sq = buf[B_SQ], *metrics = buf[B_METRICS], *rewards = buf[B_REWARDS];
    uint8_t *dones = buf[B_DONES];
    float *w = buf[B_WORK];
    float *obs = w; w += B * D;
    float *fin = w; w += B * D;
    float *act = w; w += B * A;
    float *mu = w; w += B * A;
    float *pi_acts = w; w += acts_floats(P, B);
    float *vf_acts = w; w += acts_floats(P, 2 * B);
    float *values = w; w += 2 * B;
    float *adv = w; w += B;
    float *ret = w; w += B;
    float *scratch = w; w += B;
    float *grad = w; w += P->size;
    float *g1 = w; w += B * H;
    float *g2 = w; w += B * H;
    float *g_mu = w; w += B * A;
    float *wt = w; w += P->size;
    float *gathered = w; w += B * D;
    for (int st = 0; st < (P->shared ? 1 : 2); st++)
        for (int64_t l = 0; l < P->depth; l++)
            transpose(flat + P->off_w[st][l], P->hidden[l], l == 0 ? P->in_dim[st] : P->hidden[l - 1],
                      wt + P->off_w[st][l]);
    const float *log_std = flat + P->off_log_std;
    float sigma[16];
    for (int64_t j = 0; j < A; j++) sigma[j] = expf(log_std[j]);

    /* rollout (rollout_step x n): act with the policy mean + sigma * noise, step, observe, auto-reset */
    for (int64_t i = 0; i < N; i++) pm_observe(&P->env, &s, i, (int)P->privileged, obs + i * D);
    int64_t ends = 0;
    for (int64_t t = 0; t < n; t++) {
        const float *h = stack_forward(P, flat, wt, 0, obs + t * N * D, N, D, pi_acts, B, t * N);
        float *mu_t = mu + t * N * A, *a = act + t * N * A;
        linear(h, N, hl, hl, flat + P->off_pi_w, flat + P->off_pi_b, A, mu_t);
        for (int64_t r = 0; r < N * A; r++) a[r] = mu_t[r] + sigma[r % A] * noise[t * N * A + r];
        for (int64_t i = 0; i < N; i++) {
            float clipped[16];
            for (int64_t j = 0; j < A; j++) clipped[j] = a[i * A + j] < -1.0f ? -1.0f : (a[i * A + j] > 1.0f ? 1.0f : a[i * A + j]);
            rewards[t * N + i] = (float)pm_agent_step(&P->env, &s, sched, i, clipped);
            pm_observe(&P->env, &s, i, (int)P->privileged, fin + (t * N + i) * D);
            int done = s.t[i] >= P->env.episode_steps;  /* truncation; eq. 35 has no terminal state */
            dones[t * N + i] = (uint8_t)done;
            ends += done;
            if (done) pm_auto_reset(&s, &p, i);
            if (t + 1 < n) pm_observe(&P->env, &s, i, (int)P->privileged, obs + ((t + 1) * N + i) * D);
        }
    }

    /* values at obs, and at the final observations: those equal the next step's obs (whose values are already
     * there, row by row the same arithmetic) except after the last step and at episode ends */
    if (!P->shared) {
        const float *h_vf = stack_forward(P, flat, wt, 1, obs, B, D, vf_acts, B, 0);
        linear(h_vf, B, hl, hl, flat + P->off_vf_w, flat + P->off_vf_b, 1, values);
    } else {  /* the trunk at obs is the policy's */
        linear(last_layer(P, pi_acts, B), B, hl, hl, flat + P->off_vf_w, flat + P->off_vf_b, 1, values);
    }
    int64_t m = 0;
    for (int64_t b = 0; b < B; b++)
        if (b >= B - N || dones[b]) memcpy(gathered + (m++) * D, fin + b * D, sizeof(float) * D);
    const float *h_fin = stack_forward(P, flat, wt, P->shared ? 0 : 1, gathered, m, D, vf_acts + acts_floats(P, B), m, 0);
    linear(h_fin, m, hl, hl, flat + P->off_vf_w, flat + P->off_vf_b, 1, scratch);
    for (int64_t b = 0, j = 0; b < B; b++)
        values[B + b] = (b >= B - N || dones[b]) ? scratch[j++] : values[b + N];
    const float *nv = values + B;

    /* advantages and returns (terminated is always false here) */
    if (!P->gae) {  /* nstep_returns */
        for (int64_t i = 0; i < N; i++) {
            int64_t b = (n - 1) * N + i;
            float r = (float)P->gamma * nv[b] + rewards[b];
            ret[b] = r;
            for (int64_t t = n - 2; t >= 0; t--) {
                b = t * N + i;
                r = rewards[b] + (dones[b] ? (float)P->gamma * nv[b] : (float)P->gamma * r);
                ret[b] = r;
            }
        }
        for (int64_t b = 0; b < B; b++) adv[b] = ret[b] - values[b];
    } else {  /* gae_advantages */
        float g = (float)P->gamma, gl = (float)(P->gamma * P->gae_lambda);
        for (int64_t i = 0; i < N; i++) {
            int64_t b = (n - 1) * N + i;
            float acc = rewards[b] + g * nv[b] - values[b];
            adv[b] = acc;
            for (int64_t t = n - 2; t >= 0; t--) {
                b = t * N + i;
                float delta = rewards[b] + g * nv[b] - values[b];
                acc = delta + (dones[b] ? 0.0f : gl) * acc;
                adv[b] = acc;
            }
        }
        for (int64_t b = 0; b < B; b++) ret[b] = adv[b] + values[b];
    }
    double value_loss = 0.0, ret_mean = 0.0, res_mean = 0.0;
    for (int64_t b = 0; b < B; b++) {
        double d = (double)ret[b] - values[b];
        value_loss += d * d; ret_mean += ret[b]; res_mean += d;
    }
    value_loss /= B; ret_mean /= B; res_mean /= B;
    double ret_var = 0.0, res_var = 0.0;
    for (int64_t b = 0; b < B; b++) {
        double d = (double)ret[b] - values[b] - res_mean, e = ret[b] - ret_mean;
        res_var += d * d; ret_var += e * e;
    }
    ret_var /= (double)(B - 1); res_var /= (double)(B - 1);
    if (P->normalize_advantage) {
        double mean = 0.0, var = 0.0;
        for (int64_t b = 0; b < B; b++) mean += adv[b];
        mean /= B;
        for (int64_t b = 0; b < B; b++) var += (adv[b] - mean) * (adv[b] - mean);
        float sd = (float)sqrt(var / (double)(B - 1));
        for (int64_t b = 0; b < B; b++) adv[b] = (adv[b] - (float)mean) / (sd + 1e-8f);
    }

    /* eq. 31 loss gradients w.r.t. mean, log-std and value (a2c_update) */
    double policy_loss = 0.0, entropy = 0.0;
    float g_log_std[16];
    for (int64_t j = 0; j < A; j++) { g_log_std[j] = 0.0f; entropy += log_std[j] + 0.5 * (1.0 + LOG_2PI); }
    for (int64_t b = 0; b < B; b++) {
        float wb = adv[b] / (float)B, lp = 0.0f;
        for (int64_t j = 0; j < A; j++) {
            float inv = expf(-log_std[j]), z = (act[b * A + j] - mu[b * A + j]) * inv, m = mu[b * A + j];
            lp += -0.5f * z * z - log_std[j] - 0.5f * (float)LOG_2PI;
            float gm = -wb * z * inv;
            if (P->bound_coef > 0.0) {
                float over = fabsf(m) - 1.0f;
                if (over > 0.0f) gm += (float)(2.0 * P->bound_coef / B) * over * ((m > 0.0f) - (m < 0.0f));
            }
            g_mu[b * A + j] = gm;
            g_log_std[j] += -wb * (z * z - 1.0f);
        }
        policy_loss += (double)adv[b] * lp;
    }
    policy_loss = -policy_loss / B;

    /* backward (networks.backward) into grad */
    memset(grad, 0, sizeof(float) * P->size);
    for (int64_t j = 0; j < A; j++) grad[P->off_log_std + j] = g_log_std[j] - (float)P->ent_coef;
    float *g_v = values + B;  /* reuse: V(next) is no longer needed; holds dL/dV at obs */
    for (int64_t b = 0; b < B; b++) g_v[b] = (float)(2.0 * P->vf_coef / B) * (values[b] - ret[b]);
    const float *h_pi = last_layer(P, pi_acts, B);
    memset(g1, 0, sizeof(float) * B * hl);
    head_backward(h_pi, B, hl, flat + P->off_pi_w, g_mu, A, grad + P->off_pi_w, grad + P->off_pi_b, g1);
    if (!P->shared) {
        stack_backward(P, flat, 0, obs, D, pi_acts, B, g1, g2, grad);
        memset(g1, 0, sizeof(float) * B * hl);
        head_backward(last_layer(P, vf_acts, B), B, hl, flat + P->off_vf_w, g_v, 1, grad + P->off_vf_w,
                      grad + P->off_vf_b, g1);
        stack_backward(P, flat, 1, obs, D, vf_acts, B, g1, g2, grad);
    } else {  /* both heads feed the trunk */
        head_backward(h_pi, B, hl, flat + P->off_vf_w, g_v, 1, grad + P->off_vf_w, grad + P->off_vf_b, g1);
        stack_backward(P, flat, 0, obs, D, pi_acts, B, g1, g2, grad);
    }

    /* λζ clipping and eq. 32 RMSProp */
    double sumsq = 0.0;
#pragma omp simd reduction(+ : sumsq)
    for (int64_t k = 0; k < P->size; k++) sumsq += (double)grad[k] * grad[k];
    float norm = (float)sqrt(sumsq);
    float scale = (float)P->max_grad_norm / (norm + 1e-6f);
    if (scale > 1.0f) scale = 1.0f;
    rmsprop(flat, sq, grad, P->size, scale, (float)P->rms_alpha, (float)P->lr, (float)P->rms_eps);
    metrics[0] = (float)policy_loss;
    metrics[1] = (float)value_loss;
    metrics[2] = (float)entropy;
    metrics[3] = norm;
    metrics[4] = (float)(1.0 - res_var / (ret_var + 1e-8));
    return ends;
}

/* ------------------------------------------------------------------ many iterations per call */

/* out[i] = sum over t of x[t, i], x [rows, cols], as torch's `x.sum(0)` adds a contiguous [rows, cols] float32 block
 * over its outer dim (aten/src/ATen/native/cpu/SumKernel.cpp, multi_row_sum): rows go into level 0 in blocks of 16;
 * after each block the levels carry upwards (level j after blocks that are multiples of 16^j); at the end the last
 * partial block is in level 0 and levels 1-3 are added to it.  Up to 17 rows this is the plain sequential sum.
 * algorithms/native checks it against torch for the trainer's shape before it relies on it. */
void a2c_outer_sum(const float *x, int64_t rows, int64_t cols, float *out) {
    enum { LEVELS = 4, STEP = 16 };
    for (int64_t c = 0; c < cols; c++) {
        float acc[LEVELS] = {0.0f, 0.0f, 0.0f, 0.0f};
        int64_t i = 0;
        while (i + STEP <= rows) {
            for (int64_t j = 0; j < STEP; j++, i++) acc[0] += x[i * cols + c];
            for (int64_t j = 1; j < LEVELS; j++) {
                acc[j] += acc[j - 1];
                acc[j - 1] = 0.0f;
                if ((i & ((int64_t)(STEP - 1) << (4 * j))) != 0) break;
            }
        }
        for (; i < rows; i++) acc[0] += x[i * cols + c];
        for (int64_t j = 1; j < LEVELS; j++) acc[0] += acc[j];
        out[c] = acc[0];
    }
}

/* `count` iterations, the noise of iteration k at noise + k n N A.  Each adds its metrics to metric_sum [5] (as
 * Checkpoints.add_metrics); every iteration but the last adds its rewards summed over the rollout to ep_return [N]
 * and n to ep_length [N] (as FusedRollout.iterate does for a rollout without an episode end); the last iteration's
 * rewards and dones stay in their buffers for the caller.  An episode end before the last iteration stops the call:
 * returns the number of iterations run (count, unless one ended an episode early). */
int64_t a2c_iterations(const a2c_params *P, void **buf, int64_t count, float *metric_sum, float *ep_return,
                       int64_t *ep_length) {
    const int64_t N = P->env.N, n = P->n, stride = n * N * P->act_dim;
    void *table[B_COUNT];
    memcpy(table, buf, sizeof table);
    const float *metrics = buf[B_METRICS], *rewards = buf[B_REWARDS];
    float sums[N > 0 ? N : 1];
    for (int64_t k = 0; k < count; k++) {
        table[B_NOISE] = (float *)buf[B_NOISE] + k * stride;
        int64_t ends = a2c_iteration(P, table);
        for (int j = 0; j < 5; j++) metric_sum[j] += metrics[j];
        if (k + 1 == count) break;
        if (ends) return k + 1;
        a2c_outer_sum(rewards, n, N, sums);
        for (int64_t i = 0; i < N; i++) { ep_return[i] += sums[i]; ep_length[i] += n; }
    }
    return count;
}
