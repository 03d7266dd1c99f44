/* The C point mass (point_mass.h) as a library for Python: a batched agent step over N envs.
 * Used by the gym env of the SB3 benchmark (bench/point_mass_gym.py); envs/native/__init__.py binds it. */
#include "point_mass.h"

/* the state pointer table, in pm_state's order (envs/native/__init__.py: STATE) */
enum { S_X, S_XD, S_TARGET, S_WLOG, S_FD, S_WALL, S_FENV, S_FOPE, S_HASWALL, S_T, S_SCEN, S_SLOT, S_COUNT };

int64_t pm_params_size(void) { return (int64_t)sizeof(pm_params); }
int64_t pm_state_count(void) { return S_COUNT; }

/* one agent step of all N envs: actions [N, 4]; writes rewards [N] and the observation after the step [N, 3] */
void pm_step(const pm_params *P, void **buf, const double *sched, const float *actions, double *rewards, float *obs) {
    pm_state s = {buf[S_X], buf[S_XD], buf[S_TARGET], buf[S_WLOG], buf[S_FD], buf[S_WALL], buf[S_FENV], buf[S_FOPE],
                  buf[S_HASWALL], buf[S_T], buf[S_SCEN], buf[S_SLOT]};
    for (int64_t i = 0; i < P->N; i++) {
        rewards[i] = pm_agent_step(P, &s, sched, i, actions + 4 * i);
        pm_observe(P, &s, i, 0, obs + 3 * i);
    }
}
