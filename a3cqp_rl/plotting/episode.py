"""Episode plots like the paper's Fig. 7/8 (one Panda episode: weights, f_d, e, f_env, f_ope on one axis of L, the
scene's own signal at the bottom, the leading task shaded) and an image strip of the MuJoCo scene rendered offscreen.

Both take data (arrays, or an episode .npz as written by `a3cqp evaluate --scene ... --out RUN`), not env objects.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

__all__ = ["plot_episode", "load_episode", "render_strip", "snapshot_events", "AXES", "TASK_COLOURS"]

AXES = ("x", "y", "z", "rx", "ry", "rz")
TASK_COLOURS = {"IK": "#9ecae1", "AC": "#a1d99b", "FC": "#fc9272"}
"""Fig. 7/8's colours: blue IK, green AC, red FC."""
_TASKS = ("IK", "AC", "FC")
_LETTERS = "ABCDEFGHIJKL"
TIE = 0.05
"""Weights closer than this share the lead: the shading then mixes the two tasks' colours (a saturated blend such as
w1 = w3 = 0.499 is a tie that argmax would give to the lower index)."""
MIN_SPAN = 0.1
"""Shorter runs of one shading [s] join the run before them (a tie that flickers would draw stripes)."""
_SHARED = ((0, 1), (0, 2), (1, 2))


def load_episode(path: str | Path) -> dict[str, np.ndarray]:
    """Arrays of an episode .npz (a run folder: its episode_learned.npz)."""
    path = Path(path)
    if path.is_dir():
        path = path / "episode_learned.npz"
    if not path.is_file():
        others = sorted(p.stem.removeprefix("episode_") for p in path.parent.glob("episode_*.npz"))
        hint = (f"this run has {', '.join(others)}: pick one with --controller" if others
                else "write one with `a3cqp evaluate --scene ... --out`")
        raise FileNotFoundError(f"episode file not found: {path} ({hint})")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError) as exc:  # numpy's own text would suggest loading pickles
        raise ValueError(f"{path} is not an episode file of `a3cqp evaluate --scene ... --out` "
                         f"({type(exc).__name__})") from None
    missing = [k for k in ("time", "phase", "e_local", "f_env_local", "f_ope_local", "weights") if k not in data]
    if missing:
        torch_file = any(k.endswith("data.pkl") or "/data/" in k for k in data)  # a torch zip read as an .npz
        what = ("it is a torch file (a policy or checkpoint: `a3cqp plot policy-map` draws a policy)" if torch_file
                else f"it lacks {missing}")
        raise ValueError(f"{path} is not an episode file of `a3cqp evaluate --scene ... --out`: {what}")
    return data


PULL_FORCE = 5.0
"""|f_ope| [N] that marks the operator pulling (past the grasp's 0.2-s fade-in)."""


def snapshot_events(ep: dict[str, np.ndarray], frames: int = 6) -> list[tuple[float, str]]:
    """Up to `frames` (time [s], name) moments worth a snapshot, as Fig. 7's (A)-(F), from the episode's own signals.

    Peg-in-hole (a `depth` signal): the first contact and the tip in the bore (the scene's own `contact_time` and
    `bore_time`, which `a3cqp evaluate --out` records with the episode), the end of the insertion phase, the operator
    pulling (|f_ope| > 5 N in the disengagement), the tip back above the rim; for each later cycle its insertion's
    end and its peg out; the end. Other scenes: the start of each phase after the first, then the end. Moments the
    episode never reaches are left out, and so is one within 0.05 s of the moment before; evenly spaced times stand
    in when only the end is left. With more moments than `frames`, frames spread over them, the first and the end
    kept (Fig. 8's (A)-(F) span the whole episode)."""
    t = np.asarray(ep["time"], dtype=float)
    names = [str(x) for x in ep.get("phase_names", [])]
    phase = np.asarray(ep["phase"]) if "phase" in ep else np.zeros(len(t), dtype=np.int64)
    events: list[tuple[float, str]] = []

    def first(mask: np.ndarray, name: str) -> int | None:
        idx = np.flatnonzero(mask)
        if len(idx):
            events.append((float(t[idx[0]]), name))
            return int(idx[0])
        return None

    after = np.arange(len(t))
    if "depth" in ep and "insert" in names:
        depth = np.asarray(ep["depth"], dtype=float)
        insert = phase == names.index("insert")
        for key, name in (("contact_time", "first contact"), ("bore_time", "in the bore")):
            when = np.asarray(ep.get(key, [np.nan]), dtype=float).reshape(-1)[0]
            if np.isfinite(when):
                events.append((float(when), name))
        ends = np.flatnonzero(insert[:-1] & ~insert[1:])
        pull = np.linalg.norm(np.asarray(ep["f_ope_local"])[:, :3], axis=1) > PULL_FORCE
        for c, end in enumerate(ends):
            cycle = "" if c == 0 else f" ({c + 1})"
            events.append((float(t[end + 1]), "insertion over" + cycle))
            if "disengage" in names:
                d = (first((after > end) & (phase == names.index("disengage")) & pull, "operator pulls")
                     if c == 0 else next(iter(np.flatnonzero((after > end) & pull)), None))
                if d is not None:
                    first((after > d) & (depth < 0.0), "peg out" + cycle)
    else:
        for s, _e, _lab in _spans(phase)[1:]:
            events.append((float(t[s]), names[int(phase[s])] if names else f"phase {int(phase[s])}"))
    events.append((float(t[-1]), "end"))
    kept: list[tuple[float, str]] = []
    for te, name in sorted(events, key=lambda e: e[0]):
        if not kept or te > kept[-1][0] + 0.05:  # two snapshots closer than that look alike
            kept.append((te, name))
    if len(kept) < 2:  # nothing happened before the end: evenly spaced
        return [(float(x), "") for x in np.linspace(t[0], t[-1], frames + 2)[1:-1]]
    if len(kept) > frames:
        return [kept[i] for i in np.unique(np.linspace(0, len(kept) - 1, frames).round().astype(int))]
    return kept


def leading_task(w: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The shading's label per sample from weights [T, 3]: 0-2 one task leads (IK, AC, FC), 3-5 two share the lead
    within TIE (IK+AC, IK+FC, AC+FC); runs shorter than MIN_SPAN [s] take the label before them."""
    order = np.argsort(-w, axis=1, kind="stable")
    top, second = order[:, 0], order[:, 1]
    gap = np.take_along_axis(w, order[:, :1], 1)[:, 0] - np.take_along_axis(w, order[:, 1:2], 1)[:, 0]
    shared = 2 + top + second  # 3 + the pair's index in _SHARED: (0, 1) -> 3, (0, 2) -> 4, (1, 2) -> 5
    lab = np.where(gap < TIE, shared, top)
    for s, e, _ in _spans(lab)[1:]:
        if t[min(e, len(t) - 1)] - t[s] < MIN_SPAN:
            lab[s:e] = lab[s - 1]
    return lab


def _shade_colour(label: int) -> str | tuple:
    """A single task's colour, or the mean of the two that share the lead."""
    import matplotlib.colors as mcolors

    if label < 3:
        return TASK_COLOURS[_TASKS[label]]
    a, b = _SHARED[label - 3]
    return tuple((np.array(mcolors.to_rgb(TASK_COLOURS[_TASKS[a]])) + mcolors.to_rgb(TASK_COLOURS[_TASKS[b]])) / 2)


def _shade_name(label: int) -> str:
    return f"{_TASKS[label]} leads" if label < 3 else " + ".join(_TASKS[i] for i in _SHARED[label - 3]) + " share"


def _robust_ylim(a, y: np.ndarray, unit: str) -> None:  # noqa: ANN001
    """Limits that show the working range: 1-ms contact spikes beyond 4x the 99th percentile are clipped (and said),
    a signal at round-off (|y| < 1e-3) gets a ±1 range instead of its noise blown up."""
    y = np.asarray(y, dtype=float)
    y = y[np.isfinite(y)]
    if not len(y):
        return
    lo, hi = np.percentile(y, [0.5, 99.5])
    span = max(hi - lo, 1e-9)
    if np.abs(y).max() < 1e-3:
        a.set_ylim(-1.0, 1.0)
    elif y.min() < lo - 4 * span or y.max() > hi + 4 * span:
        a.set_ylim(lo - 0.3 * span, hi + 0.3 * span)
        a.text(0.005, 0.03, f"spikes to {y.min():.0f} / {y.max():.0f} {unit} clipped", transform=a.transAxes,
               fontsize=7, color="0.3")


def _spans(labels: np.ndarray) -> list[tuple[int, int, int]]:
    """(start, end, label) runs of equal consecutive labels."""
    change = np.flatnonzero(np.diff(labels)) + 1
    starts = np.concatenate([[0], change])
    ends = np.concatenate([change, [len(labels)]])
    return [(int(a), int(b), int(labels[a])) for a, b in zip(starts, ends)]


def plot_episode(ep: dict[str, np.ndarray], out: str | Path, axis: str = "z", title: str | None = None) -> Path:
    """Fig. 7/8-style figure of one episode on local axis `axis`; returns the written path (PNG or PDF)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if axis not in AXES:
        raise ValueError(f"axis must be one of {AXES}, got {axis!r}")
    k = AXES.index(axis)
    t = np.asarray(ep["time"], dtype=float)
    if len(t) < 2:
        raise ValueError("the episode has fewer than two steps")
    w = np.asarray(ep["weights"])[:, k]
    rot = k >= 3
    lin, force = ("rad", "N m") if rot else ("m", "N")
    scene = str(ep.get("scene", ""))
    bottom = []
    if "misalign_translation" in ep:
        bottom = [("misalignment", [(1e3 * ep["misalign_translation"], "translation [mm]"),
                                    (np.degrees(ep["misalign_rotation"]), "rotation [deg]")])]
    elif "x_d" in ep:
        bottom = [("reference [m]", [(ep["x_d"], "x_d"), (ep["y_d"], "y_d")])]
    rows = 5 + len(bottom)
    fig, ax = plt.subplots(rows, 1, figsize=(11, 2.0 * rows + 1), sharex=True)
    for i, name in enumerate(("w1 IK", "w2 AC", "w3 FC")):
        ax[0].plot(t, w[:, i], color=("C0", "C2", "C3")[i], label=name)
    ax[0].set_ylabel(f"weights ({axis})")
    ax[0].set_ylim(-0.05, 1.05)
    ax[1].plot(t, np.asarray(ep["f_d"])[:, k], color="C3", label=f"f_d [{force}]")
    ax[1].set_ylabel(f"f_d [{force}]\n(the tool's push)")
    ax[2].plot(t, np.asarray(ep["e_local"])[:, k], color="C0", label=f"e [{lin}]")
    ax[2].set_ylabel(f"e [{lin}]")
    ax[3].plot(t, np.asarray(ep["f_env_local"])[:, k], color="C3", label=f"f_env [{force}]")
    ax[3].set_ylabel(f"f_env [{force}]\n(on the tool: < 0 pushes back)")
    _robust_ylim(ax[3], np.asarray(ep["f_env_local"])[:, k], force)
    ax[4].plot(t, np.asarray(ep["f_ope_local"])[:, k], color="C2", label=f"f_ope [{force}]")
    ax[4].set_ylabel(f"f_ope [{force}]")
    _robust_ylim(ax[4], np.asarray(ep["f_ope_local"])[:, k], force)
    for j, (label, curves) in enumerate(bottom):
        a = ax[5 + j]
        for c, (y, name) in enumerate(curves):
            a.plot(t, y, color=f"C{c + 4}", label=name)
        a.set_ylabel(label)
    # shading: the task leading this axis (largest weight, or two within TIE), as Fig. 7/8's patches
    lead = leading_task(w, t)
    for a in ax:
        for s, e, lab in _spans(lead):
            a.axvspan(t[s], t[min(e, len(t) - 1)], color=_shade_colour(lab), alpha=0.35, lw=0)
        a.grid(alpha=0.3)
        a.legend(loc="upper right", fontsize=8)
    # the procedure's phases as thin lines with their names
    if "phase" in ep and "phase_names" in ep:
        names = [str(x) for x in ep["phase_names"]]
        for j, (s, _e, lab) in enumerate(_spans(np.asarray(ep["phase"]))):
            for a in ax:
                a.axvline(t[s], color="0.4", lw=0.6, ls=":")
            # staggered heights: phases a second apart would print their names over each other
            ax[0].text(t[s], 1.07 + 0.16 * (j % 2), names[lab], fontsize=7, va="bottom")
    # the image strip's moments (render_strip), lettered as Fig. 7's snapshots
    for j, ((te, name), letter) in enumerate(zip(snapshot_events(ep) if "phase" in ep else [], _LETTERS)):
        if name:
            for a in ax:
                a.axvline(te, color="0.15", lw=0.8, ls="--")
            # staggered: moments a fraction of a second apart would print their letters on top of each other
            ax[-1].text(te, 0.97 - 0.14 * (j % 3), f" {letter}", transform=ax[-1].get_xaxis_transform(), fontsize=8,
                        va="top", fontweight="bold")
    ax[-1].set_xlabel("time [s]")
    shown = sorted(set(range(3)) | set(np.unique(lead).tolist()))
    handles = [matplotlib.patches.Patch(color=_shade_colour(i), alpha=0.5, label=_shade_name(i)) for i in shown]
    fig.legend(handles=handles, loc="upper left", ncol=len(handles), fontsize=8, bbox_to_anchor=(0.01, 0.985))
    fig.suptitle(title or f"{scene} episode, local axis {axis}", y=0.995)
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def render_strip(ep: dict[str, np.ndarray], out: str | Path, frames: int = 6, size: tuple[int, int] = (360, 480),
                 times: list[float] | None = None) -> Path:
    """Offscreen MuJoCo snapshots of the episode (its recorded joint angles in its scene) in a row; returns the path.

    Needs an OpenGL backend (MUJOCO_GL=egl or osmesa). MuJoCo picks its backend when it is first imported, so when
    the process's one cannot render offscreen the frames are drawn in a fresh interpreter with MUJOCO_GL=egl, then
    osmesa; RuntimeError when none works.
    """
    try:
        return _render_strip(ep, out, frames, size, times)
    except RuntimeError as first:
        import subprocess
        import sys
        import tempfile

        with tempfile.TemporaryDirectory() as tmp:
            src = Path(tmp) / "episode.npz"
            np.savez(src, **ep)
            for backend in ("egl", "osmesa"):
                code = ("import sys; from a3cqp_rl.plotting.episode import _render_strip, load_episode; "
                        f"_render_strip(load_episode(sys.argv[1]), sys.argv[2], {frames}, {tuple(size)}, {times!r})")
                env = {**os.environ, "MUJOCO_GL": backend, "PYOPENGL_PLATFORM": backend}
                done = subprocess.run([sys.executable, "-c", code, str(src), str(out)], env=env, capture_output=True)
                if done.returncode == 0:
                    return Path(out)
        raise first


def _render_strip(ep: dict[str, np.ndarray], out: str | Path, frames: int, size: tuple[int, int],
                  times: list[float] | None) -> Path:
    """render_strip in this process (its MuJoCo GL backend)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import mujoco

    from a3cqp_rl.robot.mjcf import compose_mjcf

    for key in ("q", "tool", "scene_xml"):
        if key not in ep:
            raise ValueError(f"the episode has no {key!r}: record it with `a3cqp evaluate --scene ... --out`")
    model = mujoco.MjModel.from_xml_string(compose_mjcf(str(ep["tool"]), str(ep["scene_xml"])))
    data = mujoco.MjData(model)
    try:
        renderer = mujoco.Renderer(model, size[0], size[1])
    except Exception as exc:  # no GL context: EGL/OSMesa missing
        raise RuntimeError(f"no OpenGL backend for offscreen rendering ({type(exc).__name__}: {exc}); "
                           "install EGL or OSMesa and set MUJOCO_GL=egl or MUJOCO_GL=osmesa") from None
    t = np.asarray(ep["time"], dtype=float)
    moments = snapshot_events(ep, frames) if times is None else [(float(x), "") for x in times]
    opt = mujoco.MjvOption()
    opt.geomgroup[:] = 1
    images = []
    tcp = model.site("tcp").id
    for tt, name in moments:
        i = int(np.argmin(np.abs(t - tt)))
        data.qpos[:7] = ep["q"][i]
        mujoco.mj_forward(model, data)
        cam = mujoco.MjvCamera()
        cam.lookat[:] = data.site_xpos[tcp] + np.array([0.0, 0.0, 0.05])
        cam.distance, cam.azimuth, cam.elevation = 0.55, 150.0, -20.0
        renderer.update_scene(data, camera=cam, scene_option=opt)
        images.append((t[i], name, renderer.render().copy()))
    renderer.close()
    fig, ax = plt.subplots(1, len(images), figsize=(3.2 * len(images), 2.8))
    for a, (ti, name, im), label in zip(np.atleast_1d(ax), images, _LETTERS):
        a.imshow(im)
        a.set_title(f"({label}) {name + ', ' if name else ''}t = {ti:.1f} s", fontsize=9)
        a.axis("off")
    fig.tight_layout()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out
