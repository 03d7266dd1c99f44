/* MuJoCo's contact filter callback (mjcb_contactfilter) with an exact pre-filter of tool-box pairs
   (a3cqp_rl/robot/contact_filter.py registers the models and installs it).

   MuJoCo calls the filter for every candidate geom pair its broad phase passes, in place of its contype/conaffinity
   test, so the callback applies that test first, for every pair of every model in the process. For a registered
   (model, data) it then drops a pair of a tool geom (bounded by a cylinder: its own frame's axis `axis`, half-length
   h, radius rho) and a box geom when a plane normal to one of the box's axes separates them by more than `slack`
   plus the pair's margin and gaps. The test clips the cylinder to the box's slab along each other axis first, so a
   peg half inside a bore is tested with the part that is level with a box. MuJoCo makes no contact of a pair
   separated by more than its margin, so every contact, and every number after it, stays as it was.

   No MuJoCo headers: the callback reads mjModel's geom_contype and geom_conaffinity through their offsets in the
   struct, which the Python side finds once per process from the arrays the bindings expose.

   A pair the box's axes do not separate is tested once more, through the box's slabs: for each pair of box axes
   (w, u) the part of the cylinder inside the slab |x_w| <= e_w + gap is bounded along u by the cylinder's support
   along e_u + lam e_w (any lam gives a valid bound; the best one per smooth piece is the root of a quadratic). A
   peg tilted in a bore reaches a box's radial slab only with its upper part, above the box's top, where the
   clipping above takes the whole end disc into the slab (docs/panda.md, "The collision pass's floor under an exact
   pre-filter"). */
#include <math.h>
#include <stddef.h>
#include <stdint.h>

typedef struct {
  const void* m;              /* mjModel* and mjData* of the registration (NULL: a free slot) */
  const void* d;
  const double* size;         /* the model's geom_size [ngeom, 3], geom_margin, geom_gap */
  const double* margin;
  const double* gap;
  const double* xpos;         /* the data's geom_xpos [ngeom, 3] and geom_xmat [ngeom, 9] */
  const double* xmat;
  const int8_t* role;         /* per geom: 1 tool, 2 box, 0 neither */
  const double* cylinder;     /* per geom [axis, h, rho] (tools) */
  double slack;               /* m */
  int64_t tested, dropped;    /* counters: tool-box pairs seen, pairs dropped */
  int64_t dropped_slab;       /* of the dropped: by the bound through a slab (slab_separated) */
} cf_entry;

#define CF_SLOTS 256
static cf_entry slots[CF_SLOTS];
static int used = 0;          /* slots [0, used) may be taken */
static ptrdiff_t off_contype = -1, off_conaffinity = -1;

void cf_set_offsets(int64_t contype, int64_t conaffinity) {
  off_contype = (ptrdiff_t)contype;
  off_conaffinity = (ptrdiff_t)conaffinity;
}

/* Copy `e` into a free slot (its `m` written last, so that a concurrent reader never matches a half-written
   slot); returns the slot or -1 when all are taken. */
int64_t cf_register(const cf_entry* e) {
  for (int i = 0; i < CF_SLOTS; i++) {
    if (slots[i].m != NULL) continue;
    const void* m = e->m;
    slots[i] = *e;
    slots[i].m = NULL;
    slots[i].tested = slots[i].dropped = slots[i].dropped_slab = 0;
    __sync_synchronize();
    slots[i].m = m;
    if (i >= used) used = i + 1;
    return i;
  }
  return -1;
}

void cf_unregister(int64_t slot) {
  if (slot >= 0 && slot < CF_SLOTS) slots[slot].m = NULL;
}

/* Pairs seen, dropped, and dropped by the bound through a slab of registration `slot` ([3] int64). */
void cf_counts(int64_t slot, int64_t* out) {
  out[0] = slots[slot].tested;
  out[1] = slots[slot].dropped;
  out[2] = slots[slot].dropped_slab;
}

/* A lower bound on n . x over the cylinder's points x with |x_w| <= L, for n = e_u + lam e_w (box frame; the
   cylinder's centre has coordinates cu, cw and its axis au, aw along e_u, e_w): the cylinder's support along -n,
   plus lam x_w >= -|lam| L. Any lam gives a valid bound (weak duality). */
static double slab_bound(double cu, double cw, double au, double aw, double h, double rho, double L, double lam) {
  double na = au + lam * aw, q = 1.0 + lam * lam - na * na;
  return cu + lam * cw - h * fabs(na) - rho * sqrt(q > 0.0 ? q : 0.0) - fabs(lam) * L;
}

/* 1 when the bound of slab_bound exceeds `target` for some lam: the best lam of each piece where the two absolute
   values keep their signs (the root of a quadratic; pieces split at lam = 0 and au + lam aw = 0), and the breaks. */
static int slab_separated(double cu, double cw, double au, double aw, double h, double rho, double L, double target) {
  const double BIG = 1e6;  /* stands in for an unbounded piece's end (any lam is valid) */
  double A = 1.0 - aw * aw, B = -2.0 * au * aw, D = 4.0 * (1.0 - au * au - aw * aw);
  double z = fabs(aw) > 1e-12 ? -au / aw : 0.0;
  if (!(z > -BIG && z < BIG)) z = 0.0;
  double brk[4] = {-BIG, z < 0.0 ? z : 0.0, z < 0.0 ? 0.0 : z, BIG};  /* (z = 0: an empty middle piece) */
  if (D < 0.0) D = 0.0;
  if (slab_bound(cu, cw, au, aw, h, rho, L, brk[0]) > target) return 1;
  for (int i = 0; i < 3; i++) {
    double lo = brk[i], hi = brk[i + 1];
    if (!(hi > lo)) continue;
    if (slab_bound(cu, cw, au, aw, h, rho, L, hi) > target) return 1;
    double mid = lo > -BIG ? (hi < BIG ? 0.5 * (lo + hi) : lo + 1.0) : hi - 1.0;
    double s1 = mid > 0.0 ? 1.0 : -1.0, s2 = au + mid * aw > 0.0 ? 1.0 : -1.0;
    double k = (cw - s1 * L - s2 * h * aw) / rho, lam;
    if (A > 1e-12 && k * k < A) {
      lam = (k * sqrt(D / (A - k * k)) - B) / (2.0 * A);
    } else {
      lam = k > 0.0 ? hi : lo;
    }
    lam = lam < lo ? lo : (lam > hi ? hi : lam);
    if (slab_bound(cu, cw, au, aw, h, rho, L, lam) > target) return 1;
  }
  return 0;
}

/* Nonzero when the cylinder (centre c, unit axis a, half-length h, radius rho) lies farther than `gap` from the box
   (columns of R its axes; centre b, half-sizes e): 1 when a plane normal to one of the box's axes keeps them apart,
   2 when the bound through one of the box's slabs does (slab_separated). */
static int separated(const double* c, const double* a, double h, double rho, const double* b, const double* R,
                     const double* e, double gap) {
  double ac[3], dc[3], s[3];
  for (int j = 0; j < 3; j++) {
    ac[j] = a[0] * R[j] + a[1] * R[3 + j] + a[2] * R[6 + j];
    dc[j] = (c[0] - b[0]) * R[j] + (c[1] - b[1]) * R[3 + j] + (c[2] - b[2]) * R[6 + j];
    double q = 1.0 - ac[j] * ac[j];
    s[j] = rho * sqrt(q > 0.0 ? q : 0.0);  /* the cylinder's end discs reach this far along axis j */
  }
  for (int j = 0; j < 3; j++)
    if (fabs(dc[j]) - h * fabs(ac[j]) - s[j] - e[j] > gap) return 1;
  /* the cylinder's cross-sections at t in [lo, hi] are the ones that reach the slab |x_w| <= e_w + gap */
  for (int w = 0; w < 3; w++) {
    if (fabs(ac[w]) < 1e-9) continue;
    double lo = (-e[w] - gap - s[w] - dc[w]) / ac[w], hi = (e[w] + gap + s[w] - dc[w]) / ac[w];
    if (lo > hi) { double t = lo; lo = hi; hi = t; }
    if (lo < -h) lo = -h;
    if (hi > h) hi = h;
    if (lo > hi) return 1;
    for (int u = 0; u < 3; u++) {
      if (u == w) continue;
      double p0 = dc[u] + lo * ac[u], p1 = dc[u] + hi * ac[u];
      double top = (p0 > p1 ? p0 : p1) + s[u], bottom = (p0 < p1 ? p0 : p1) - s[u];
      if (bottom - e[u] > gap || -e[u] - top > gap) return 1;
    }
  }
  /* the part of the cylinder in the slab along w, bounded along u through the slab (slab_separated): a tilted peg's
     end reaches a box's slab with a thin sliver only, where the test above takes the whole end disc */
  for (int w = 0; w < 3; w++) {
    double L = e[w] + gap;
    for (int u = 0; u < 3; u++) {
      if (u == w) continue;
      double sg = dc[u] >= 0.0 ? 1.0 : -1.0;  /* the side of the box the cylinder's centre is on */
      double target = e[u] + gap;
      /* a point of the axis inside the slab and not beyond the face: no bound can exceed it */
      if (fabs(ac[w]) > 1e-12) {
        double t0 = (-L - dc[w]) / ac[w], t1 = (L - dc[w]) / ac[w];
        if (t0 > t1) { double t = t0; t0 = t1; t1 = t; }
        if (t0 < -h) t0 = -h;
        if (t1 > h) t1 = h;
        if (t0 <= t1 && (sg * (dc[u] + t0 * ac[u]) <= target || sg * (dc[u] + t1 * ac[u]) <= target)) continue;
      } else if (fabs(dc[w]) <= L && sg * dc[u] - h * fabs(ac[u]) <= target) {
        continue;
      }
      if (slab_separated(sg * dc[u], dc[w], sg * ac[u], ac[w], h, rho, L, target)) return 2;
    }
  }
  return 0;
}

/* mjfConFilt: nonzero drops the pair. */
int cf_filter(const void* m, void* d, int g1, int g2) {
  const int* ct = *(int* const*)((const char*)m + off_contype);
  const int* ca = *(int* const*)((const char*)m + off_conaffinity);
  if (!(ct[g1] & ca[g2]) && !(ct[g2] & ca[g1])) return 1;  /* MuJoCo's own test, which the callback replaces */
  for (int i = 0; i < used; i++) {
    cf_entry* e = &slots[i];
    if (e->m != m || e->d != d) continue;
    int r1 = e->role[g1], r2 = e->role[g2];
    if (!((r1 == 1 && r2 == 2) || (r1 == 2 && r2 == 1))) return 0;
    int tool = r1 == 1 ? g1 : g2, box = r1 == 1 ? g2 : g1;
    const double* R = e->xmat + 9 * tool;
    int k = (int)e->cylinder[3 * tool];
    double a[3] = {R[k], R[3 + k], R[6 + k]};
    /* MuJoCo's margin and gap of a geom pair are the sums of the geoms' (engine_collision_driver.c, getMargin) */
    double gap = e->margin[tool] + e->margin[box] + e->gap[tool] + e->gap[box] + e->slack;
    int how = separated(e->xpos + 3 * tool, a, e->cylinder[3 * tool + 1], e->cylinder[3 * tool + 2],
                        e->xpos + 3 * box, e->xmat + 9 * box, e->size + 3 * box, gap);
    e->tested++;  /* (a registration's data is stepped by one thread at a time) */
    e->dropped += how != 0;
    e->dropped_slab += how == 2;
    return how != 0;
  }
  return 0;
}
