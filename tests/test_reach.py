"""The scenes' key poses checked against the arm's reach before a trial is simulated (envs/reach.py)."""

from __future__ import annotations

import pytest

from a3cqp_rl.config import load_config
from envs.panda_eval import main
from envs.reach import reach_warning


@pytest.mark.parametrize("scene", ["peg_in_hole", "polishing", "guidance"])
def test_the_shipped_scenes_are_within_reach(scene: str) -> None:
    assert reach_warning(load_config(f"configs/panda_{scene}.yaml").panda) is None


@pytest.mark.parametrize("scene, override, says", [
    ("peg_in_hole", {"peg_in_hole": {"hole_center": [1.2, 0.0]}}, "the approach pose above the hole at (1.200"),
    ("polishing", {"polishing": {"plate_center": [0.9, 0.0]}}, "the first polishing zone at (0.930"),
    ("guidance", {"guidance": {"waypoints": [[0.1, 0.1, -0.05], [0.6, 0.0, 0.0]]}}, "waypoint 2 at"),
])
def test_a_pose_out_of_reach_is_named_with_the_config_values_that_place_it(scene: str, override: dict,
                                                                           says: str) -> None:
    warning = reach_warning(load_config(f"configs/panda_{scene}.yaml", {"panda": override}).panda)
    assert warning is not None and says in warning and f"panda.{scene}." in warning
    assert "waypoint 1 " not in warning  # only the poses out of reach


def test_a_hole_the_arm_just_reaches_is_not_warned_about() -> None:
    """(0.2, 0): IK from home stops 2 mm above the inserted pose against a joint limit, but reaches the success
    depth; IK + FC inserts there (2/2 trials, 2026-12-01). (0.8, 0): both trials fail, and the approach is 27 mm out."""
    near = load_config("configs/panda_peg_in_hole.yaml", {"panda": {"peg_in_hole": {"hole_center": [0.2, 0.0]}}})
    assert reach_warning(near.panda) is None
    far = load_config("configs/panda_peg_in_hole.yaml", {"panda": {"peg_in_hole": {"hole_center": [0.8, 0.0]}}})
    assert "IK ends 2" in reach_warning(far.panda)


def test_evaluate_warns_before_simulating(monkeypatch, capsys) -> None:  # noqa: ANN001
    from envs import panda_eval

    class Stop(Exception):
        pass

    def stop(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        raise Stop

    monkeypatch.setattr(panda_eval, "evaluate_seeds", stop)
    with pytest.raises(Stop):
        main(["--scene", "peg_in_hole", "--trials", "1", "--controllers", "ik", "--quiet",
              "--set", "panda.peg_in_hole.hole_center=[1.2, 0.0]"])
    assert "cannot reach" in capsys.readouterr().err
