"""Issue #13 item 7: photos land in `mission.photo_folder` (one folder per flight) with their pose sidecar,
and the autopilot/GCS gets CAMERA_IMAGE_CAPTURED; a colour camera gives colour photos at full resolution."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from companion.daemon.flight import FlightFolder
from companion.mission import State
from sitl_tests.daemon_harness import mission, rig


async def test_mission_photo_goes_to_the_configured_photo_folder(tmp_path: Path) -> None:
    async with rig(tmp_path) as r:
        await r.start_mission(mission('<takeoff id="takeoff" height="1.0"/><take-photo id="shot" camera="down"/>'
                                      '<land id="land"/>', name="photo"))
        ex = r.daemon.executor
        assert ex is not None
        await r.advance_until(lambda: ex.state in (State.COMPLETED, State.FAILED, State.ABORTED), max_s=40.0)
        assert ex.state is State.COMPLETED, [(a.action_id, a.result, a.message) for a in ex.results]
        flight = r.daemon.flight
        assert flight is not None
        photo_dir = Path(r.config.mission.photo_folder) / flight.path.name
        assert photo_dir.parent == tmp_path / "photos"
        image = cv2.imread(str(photo_dir / "photo-0001.png"), cv2.IMREAD_UNCHANGED)
        assert image is not None and image.shape[:2] == (160, 240)  # the camera's full resolution
        sidecar = json.loads((photo_dir / "photo-0001.json").read_text())
        assert sidecar["mission"] == "photo" and sidecar["pose"]["ok"] is True
        T = np.asarray(sidecar["pose"]["T_ned_body"])
        assert np.linalg.norm(T[:3, 3] - r.ap.truth.position_ned_m) < 1.5
        assert not (flight.path / "photos").exists()  # not in the flight folder any more
        assert r.received("CAMERA_IMAGE_CAPTURED")


def test_colour_frames_are_saved_in_colour(tmp_path: Path) -> None:
    folder = FlightFolder.create(tmp_path / "flights", lambda: 0.0, name="f", photo_root=tmp_path / "photos")
    bgr = np.zeros((48, 64, 3), np.uint8)
    bgr[..., 2] = 200  # red
    path = folder.save_photo(bgr, {"seq": 1})
    back = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert back.shape == (48, 64, 3) and int(back[0, 0, 2]) == 200 and int(back[0, 0, 0]) == 0
    assert path.parent == tmp_path / "photos" / "f"
    folder.close()
