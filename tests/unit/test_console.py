"""The console's pieces that need no browser: its address and TLS rules, the plan's geometry
in the camera's pixels (checked against the homography applied by hand), and the scene a rig
kind asks for."""

from __future__ import annotations

import numpy as np
import pytest

from rigctl.apps.console.scene import ArmsSketch, CameraScene, plan_paths_mm, shape_polygon_mm
from rigctl.apps.console.server import check_options, console_scene, parse_address
from rigctl.core.camera_model import Calibration
from rigctl.core.errors import ConfigError
from rigctl.physics.kinematics import ArmKinematics, base_transform
from rigctl.rigs.base import RigKind


def test_addresses():
    assert parse_address(None) == ("127.0.0.1", 7820)
    assert parse_address("127.0.0.1:0") == ("127.0.0.1", 0)
    assert parse_address(":8080") == ("127.0.0.1", 8080)
    assert parse_address("8080") == ("127.0.0.1", 8080)
    assert parse_address("[::1]:7820") == ("::1", 7820)
    for bad in ("nonsense", "host:99999", "1.2.3.4:port"):
        with pytest.raises(ConfigError, match="--console"):
            parse_address(bad)


def test_beyond_loopback_needs_tls(tmp_path):
    assert check_options("localhost:7820", None, None) == ("localhost", 7820)
    with pytest.raises(ConfigError, match="TLS"):
        check_options("0.0.0.0:7820", None, None)
    with pytest.raises(ConfigError, match="TLS"):
        check_options("192.168.1.20:7820", None, None)
    with pytest.raises(ConfigError, match="both"):
        check_options("127.0.0.1:7820", tmp_path / "cert.pem", None)
    with pytest.raises(ConfigError, match="no such file"):
        check_options("0.0.0.0:7820", tmp_path / "cert.pem", tmp_path / "key.pem")


def test_shapes_become_polygons():
    assert shape_polygon_mm({"rect": [1, 2, 3, 4]}) == [[1, 2], [4, 2], [4, 6], [1, 6]]
    disk = np.array(shape_polygon_mm({"disk": [10, -5, 2]}))
    assert np.allclose(np.hypot(disk[:, 0] - 10, disk[:, 1] + 5), 2)
    plan = {"agents": [{"start": [0, 0]}, {"start": [5, 5]}],
            "expected": [[[1, 0], [6, 5]], [[1, 1], [6, 6]]]}
    assert plan_paths_mm(plan) == [[[0, 0], [1, 0], [1, 1]], [[5, 5], [6, 5], [6, 6]]]
    assert plan_paths_mm({"agents": [{"start": [0, 0]}]}) is None


class _Rig:  # what CameraScene reads of a rig
    def __init__(self, calibration):
        self.camera = type("Camera", (), {"calibration": calibration})()


def test_the_plan_in_the_cameras_pixels():
    # a tilted camera: px -> mm by this homography; mm -> px is its inverse, applied by hand
    h = np.array([[0.5, 0.05, -20.0], [-0.02, -0.5, 260.0], [1e-5, 2e-5, 1.0]])
    scene = CameraScene(_Rig(Calibration(homography_px_to_mm=h.tolist())))
    inverse = np.linalg.inv(h)

    def by_hand(x, y):
        u, v, w = inverse @ [x, y, 1.0]
        return [u / w, v / w]

    plan = {"workspace": {"boundary": {"rect": [0, 0, 100, 50]},
                          "obstacles": [{"rect": [10, 10, 5, 5]}]},
            "agents": [{"start": [20, 20], "goal": [80, 30], "radius": 4}],
            "expected": [[[80, 20]], [[80, 30]]]}
    drawn = scene.of_plan(plan)
    corners = [(0, 0), (100, 0), (100, 50), (0, 50)]
    assert np.allclose(drawn["boundary"], [by_hand(*c) for c in corners], atol=0.06)
    assert np.allclose(drawn["obstacles"][0][2], by_hand(15, 15), atol=0.06)
    assert np.allclose(drawn["paths"][0], [by_hand(20, 20), by_hand(80, 20), by_hand(80, 30)],
                       atol=0.06)
    assert np.allclose(drawn["goals"], [by_hand(80, 30)], atol=0.06)
    start, edge = np.array(by_hand(20, 20)), np.array(by_hand(24, 20))
    assert drawn["radii_px"][0] == pytest.approx(np.linalg.norm(edge - start), abs=0.1)
    # no camera: nothing to draw over
    assert CameraScene(_Rig(None)).of_plan(plan)["boundary"] == []


def _kind(**scene) -> RigKind:
    return RigKind(name="spinner", description="a magnet on a stepper", plans={},
                   channels=lambda rig: [], devices=lambda rig: [], make_safe=lambda rig: {},
                   hold=lambda rig, target: None, **scene)


def test_the_page_shows_the_scene_its_rig_kind_asks_for_and_the_camera_by_default(caplog):
    from rigctl.core.registry import rig_kind

    depm = rig_kind("depm")
    rig = depm.bench_rig()
    scene, arms = console_scene(depm, rig)
    assert scene == "arms"
    # the sketch stands each arm on its base from the rig file: the base origin is the first
    # point, the EPM the last, as the arm's kinematics at those joints put it
    sketch = ArmsSketch(arms)
    assert sketch.names == list(rig.depm.arm_names)
    q = np.linspace(-0.5, 0.5, 14)
    drawn = sketch.of_joints(q.tolist())
    for i, (position, rpy, arm) in enumerate(zip(rig.depm.arm_positions_mm, rig.depm.arm_rpy_deg,
                                                 drawn["arms"])):
        kinematics = ArmKinematics(base=base_transform(np.asarray(position) * 1e-3, rpy))
        assert np.allclose(arm["points_mm"][0], position, atol=0.05)
        epm_mm = kinematics.epm_pose(q[7 * i:7 * i + 7])[0] * 1e3
        assert np.allclose(arm["points_mm"][8], epm_mm, atol=0.05)
    assert drawn["keep_out_mm"] == rig.depm.keep_out_radius_mm

    assert console_scene(rig_kind("coil-board"), rig) == ("camera", None)
    assert console_scene(_kind(), rig) == ("camera", None)  # a kind that says nothing
    # one that asks for a scene the console cannot draw gets the camera's, and a warning
    assert console_scene(_kind(scene="hologram"), rig) == ("camera", None)
    assert console_scene(_kind(scene="arms"), rig) == ("camera", None)  # no scene_of
    assert "hologram" in caplog.text and "without scene_of" in caplog.text
