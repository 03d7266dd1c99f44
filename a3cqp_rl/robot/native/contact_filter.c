/* A MuJoCo contact filter (mjcb_contactfilter) that also drops mesh-box geom pairs proven apart.

MuJoCo's own filter for a candidate pair (one that passed the broad phase, not an explicit <pair>) is the
contype/conaffinity test; this callback does that test and, for a mesh against a box, a separating-axis test along
the box's three axes: the mesh's vertices (whose convex hull is what MuJoCo collides) projected on an axis lie
wholly beyond the box's face by more than the pair's margin + gap + SLACK -> the two are apart and the narrow phase
(GJK on the hull) would return no contact, so the pair is dropped before it. Exact: the contacts found are the same,
in the same order. Why: a peg in a bore made of boxes passes MuJoCo's bounding-sphere and box filters against most
of the bore's boxes at every step although it touches at most a few, and GJK on each of them dominated the step. */

#include <mujoco/mujoco.h>

/* distance [m] beyond margin + gap by which a pair must be apart to be dropped: far above GJK's tolerance
   (opt.ccd_tolerance, 1e-6 by default) and far below the 0.25 mm radial clearance of the peg in the bore */
#define SLACK 1e-5

int a3cqp_contact_filter_version(void) { return mjVERSION_HEADER; }

static int apart(const mjModel* m, const mjData* d, int gm, int gb, mjtNum bound) {
  int mesh = m->geom_dataid[gm];
  if (mesh < 0) return 0;
  const mjtNum* pm = d->geom_xpos + 3 * gm;
  const mjtNum* Rm = d->geom_xmat + 9 * gm;
  const mjtNum* pb = d->geom_xpos + 3 * gb;
  const mjtNum* Rb = d->geom_xmat + 9 * gb;
  const mjtNum* s = m->geom_size + 3 * gb;
  mjtNum a[3][3], c[3], lo[3], hi[3];
  for (int k = 0; k < 3; k++) {  /* box axis k (column k of Rb) in the mesh frame, and the frames' offset along it */
    for (int i = 0; i < 3; i++)
      a[k][i] = Rm[i] * Rb[k] + Rm[3 + i] * Rb[3 + k] + Rm[6 + i] * Rb[6 + k];
    c[k] = (pm[0] - pb[0]) * Rb[k] + (pm[1] - pb[1]) * Rb[3 + k] + (pm[2] - pb[2]) * Rb[6 + k];
    lo[k] = 1e300;
    hi[k] = -1e300;
  }
  const float* v = m->mesh_vert + 3 * m->mesh_vertadr[mesh];
  int nv = m->mesh_vertnum[mesh];
  for (int j = 0; j < nv; j++, v += 3) {
    mjtNum x = v[0], y = v[1], z = v[2];
    for (int k = 0; k < 3; k++) {
      mjtNum p = a[k][0] * x + a[k][1] * y + a[k][2] * z;
      if (p < lo[k]) lo[k] = p;
      if (p > hi[k]) hi[k] = p;
    }
  }
  for (int k = 0; k < 3; k++) {
    mjtNum reach = s[k] + bound;
    if (c[k] + lo[k] > reach || c[k] + hi[k] < -reach) return 1;
  }
  return 0;
}

/* mjfConFilt: 1 drops the pair */
int a3cqp_contact_filter(const mjModel* m, mjData* d, int g1, int g2) {
  if (!(m->geom_contype[g1] & m->geom_conaffinity[g2]) && !(m->geom_contype[g2] & m->geom_conaffinity[g1]))
    return 1;  /* MuJoCo's own test (filterBitmask) */
  int t1 = m->geom_type[g1], t2 = m->geom_type[g2];
  int gm, gb;
  if (t1 == mjGEOM_MESH && t2 == mjGEOM_BOX) {
    gm = g1;
    gb = g2;
  } else if (t2 == mjGEOM_MESH && t1 == mjGEOM_BOX) {
    gm = g2;
    gb = g1;
  } else {
    return 0;
  }
  if (m->opt.enableflags & mjENBL_OVERRIDE) return 0;  /* margins from opt.o_margin: leave those to MuJoCo */
  mjtNum bound = m->geom_margin[g1] + m->geom_margin[g2] + m->geom_gap[g1] + m->geom_gap[g2] + SLACK;
  return apart(m, d, gm, gb, bound);
}
