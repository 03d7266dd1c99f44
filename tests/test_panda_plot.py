"""Episode plot (Fig. 7/8 layout) from data arrays, the `a3cqp plot episode` command, and the image strip."""

from __future__ import annotations

import numpy as np
import pytest

from a3cqp_rl.plotting.cli import main as plot_main
from a3cqp_rl.plotting.episode import load_episode, plot_episode, render_strip, snapshot_events
from a3cqp_rl.robot import PANDA_HOME
from a3cqp_rl.robot.scenes import HoleGeometry, hole_block_xml


def _episode(T: int = 300) -> dict[str, np.ndarray]:
    t = np.arange(T) * 0.01
    w = np.zeros((T, 6, 3))
    w[:, :, 0] = 1.0
    w[100:200, 2] = [0.1, 0.0, 0.9]  # FC leads z in the middle
    return {"time": t, "phase": (t > 1.0).astype(np.int64) + (t > 2.0), "e_local": np.zeros((T, 6)),
            "f_env_local": np.zeros((T, 6)), "f_ope_local": np.zeros((T, 6)), "weights": w, "f_d": np.zeros((T, 6)),
            "misalign_translation": np.full(T, 0.01), "misalign_rotation": np.full(T, 0.05), "depth": np.zeros(T),
            "q": np.tile(PANDA_HOME, (T, 1)), "scene": np.array("peg_in_hole"), "tool": np.array("peg_mesh"),
            "scene_xml": np.array(hole_block_xml(HoleGeometry())),
            "phase_names": np.array(["approach", "insert", "disengage"]), "phase_task": np.array(["IK", "FC", "AC"])}


def test_plot_episode_writes_a_png_and_checks_its_input(tmp_path) -> None:  # noqa: ANN001
    out = plot_episode(_episode(), tmp_path / "ep.png", axis="z")
    assert out.is_file() and out.stat().st_size > 10_000
    with pytest.raises(ValueError, match="axis"):
        plot_episode(_episode(), tmp_path / "bad.png", axis="w")


def test_plot_episode_command_reads_a_run_folder(tmp_path, capsys) -> None:  # noqa: ANN001
    np.savez_compressed(tmp_path / "episode_learned.npz", **_episode())
    assert plot_main(["episode", str(tmp_path), "--axis", "x"]) == 0
    assert (tmp_path / "episode_learned.png").is_file()
    assert set(load_episode(tmp_path)) >= {"time", "weights", "q"}
    assert plot_main(["episode", str(tmp_path / "missing")]) == 2
    assert "episode file not found" in capsys.readouterr().err
    # a run without the learned controller's episode names the ones it has
    (tmp_path / "episode_learned.npz").rename(tmp_path / "episode_ik_fc.npz")
    assert plot_main(["episode", str(tmp_path)]) == 2
    assert "this run has ik_fc: pick one with --controller" in capsys.readouterr().err
    assert plot_main(["episode", str(tmp_path), "--controller", "ik_fc"]) == 0


def test_plot_episode_says_which_file_it_wrote_and_what_is_not_an_episode(tmp_path, capsys) -> None:  # noqa: ANN001
    np.savez_compressed(tmp_path / "episode_learned.npz", **_episode())
    assert plot_main(["episode", str(tmp_path), "--out", str(tmp_path / "noext")]) == 0
    assert (tmp_path / "noext.png").is_file() and f"wrote {tmp_path / 'noext.png'}" in capsys.readouterr().out
    for out, says in ((["--out", str(tmp_path)], "is a folder: give the image's file name"),
                      (["--out", f"{tmp_path / 'new'}/"], "is a folder: give the image's file name"),
                      (["--pdf", "--out", str(tmp_path / "x.png")], "--pdf asks for a PDF but --out")):
        assert plot_main(["episode", str(tmp_path), *out]) == 2
        assert says in capsys.readouterr().err
    (tmp_path / "results.json").write_text("{}")
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    for bad in ("results.json", "other.npz"):
        assert plot_main(["episode", str(tmp_path / bad)]) == 2
        err = capsys.readouterr().err
        assert "is not an episode file" in err and "pickle" not in err


def test_render_strip_draws_the_scene_or_says_why_not(tmp_path) -> None:  # noqa: ANN001
    try:
        out = render_strip(_episode(), tmp_path / "strip.png", frames=2, size=(120, 160))
    except RuntimeError as exc:
        assert "MUJOCO_GL" in str(exc)
        pytest.skip(f"no OpenGL here: {exc}")
    assert out.is_file() and out.stat().st_size > 5_000


def test_snapshots_are_taken_at_the_moments_of_the_insertion_as_in_fig_7() -> None:
    ep = _episode()  # phases approach (t <= 1), insert, disengage (t > 2)
    t = ep["time"]
    ep["contact_time"], ep["bore_time"] = np.array([1.2]), np.array([1.5])  # the scene's, recorded by evaluate
    ep["f_env_local"][t >= 1.0, 2] = 3.0  # a sensed force before the scene's contact is not its contact
    ep["depth"][:] = np.where(t >= 1.5, 0.01, 0.0)  # in the bore from 1.5 s, back above the rim at 2.6 s
    ep["depth"][t >= 2.6] = -0.01
    ep["f_ope_local"][t >= 2.3, 2] = 8.0  # the operator pulls
    got = snapshot_events(ep)
    names = [n for _, n in got]
    assert names == ["first contact", "in the bore", "insertion over", "operator pulls", "peg out", "end"]
    np.testing.assert_allclose([x for x, _ in got], [1.2, 1.5, 2.01, 2.3, 2.6, 2.99], atol=1e-9)
    assert len(snapshot_events(ep, frames=3)) == 3
    # a peg that never touches (no contact time, or NaN): only the end of the insertion phase and the end; another
    # scene: its phase starts
    quiet = _episode()
    quiet["contact_time"] = quiet["bore_time"] = np.array([np.nan])
    assert [n for _, n in snapshot_events(quiet)] == ["insertion over", "end"]
    del quiet["depth"]
    assert [n for _, n in snapshot_events(quiet)] == ["insert", "disengage", "end"]


def test_without_any_moment_the_snapshots_are_evenly_spaced() -> None:
    ep = _episode()
    ep["phase"][:] = 0
    del ep["depth"]
    got = snapshot_events(ep, frames=4)
    assert [n for _, n in got] == [""] * 4
    np.testing.assert_allclose([x for x, _ in got], np.linspace(0.0, 2.99, 6)[1:-1])


def test_an_episode_file_is_titled_by_its_own_controller(tmp_path, capsys, monkeypatch) -> None:  # noqa: ANN001
    import a3cqp_rl.plotting.episode as episode_module

    titles = []
    real = episode_module.plot_episode
    monkeypatch.setattr(episode_module, "plot_episode", lambda data, out, **kw: titles.append(kw["title"]) or
                        real(data, out, **kw))
    np.savez_compressed(tmp_path / "episode_vic.npz", **_episode())
    assert plot_main(["episode", str(tmp_path / "episode_vic.npz")]) == 0
    assert titles[-1].startswith("peg_in_hole: vic")  # not the --controller default, learned
    assert plot_main(["episode", str(tmp_path / "episode_vic.npz"), "--controller", "equal"]) == 2
    assert "--controller equal: episode_vic.npz is the vic controller's episode" in capsys.readouterr().err


def test_the_shading_shows_two_tasks_that_share_the_lead_and_no_flicker() -> None:
    from a3cqp_rl.plotting.episode import leading_task

    t = np.arange(0.0, 3.0, 0.01)
    w = np.zeros((len(t), 3))
    w[:100] = (1.0, 0.0, 0.0)  # IK
    w[100:200] = (0.49938108, 0.0012378, 0.49938108)  # a saturated blend: an exact tie argmax gives to IK
    w[200:] = (0.0, 0.6, 0.4)  # AC
    w[250:253] = (0.0, 0.4, 0.6)  # 30 ms of FC: joins the span before it
    lab = leading_task(w, t)
    assert lab[:100].tolist() == [0] * 100 and lab[100:200].tolist() == [4] * 100 and lab[200:].tolist() == [1] * 100


def test_a_long_episodes_snapshots_spread_over_its_cycles() -> None:
    ep = _episode()  # phases approach (t <= 1), insert, disengage (t > 2)
    for k in ("time", "phase", "depth", "f_ope_local", "f_env_local", "e_local", "weights", "f_d"):
        ep[k] = np.concatenate([ep[k], ep[k], ep[k]])  # three cycles
    n = len(ep["time"]) // 3
    ep["time"] = np.arange(3 * n) * 0.01
    t = ep["time"]
    ep["contact_time"], ep["bore_time"] = np.array([1.2]), np.array([1.5])
    ep["depth"][:] = np.where((t % 3.0) >= 1.5, 0.01, 0.0)
    ep["depth"][(t % 3.0) >= 2.6] = -0.01
    ep["f_ope_local"][(t % 3.0) >= 2.3, 2] = 8.0
    got = snapshot_events(ep)
    names = [n for _, n in got]
    assert len(got) == 6 and names[0] == "first contact" and names[-1] == "end"
    assert any(n.endswith("(3)") for n in names)  # the last cycle is shown, not only the first
    assert all(b > a for (a, _), (b, _) in zip(got, got[1:]))
