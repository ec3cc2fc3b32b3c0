"""Camera path files (nerfstudio's camera_path.json, a rendered path's transforms.json) and the path through keyframes:
read into the scene's world, written back, and bad files named in one line."""

import json
import math

import pytest
import torch

from nerf_lightning.data.formats.camera_path import camera_path_meta, read_camera_path, read_dataparser_transforms
from nerf_lightning.data.formats.shared import apply_similarity
from nerf_lightning.data.scene import Views
from nerf_lightning.geometry.cameras import look_at, opengl_to_opencv
from nerf_lightning.geometry.paths import keyframe_path

# a capture's coordinates -> the scene's world, as a loader's normalisation gives it: turned, scaled, moved
WORLD_FROM_CAPTURE = torch.tensor([[0.0, -0.5, 0.0, 0.3], [0.5, 0.0, 0.0, -0.2], [0.0, 0.0, 0.5, 0.1], [0.0, 0.0, 0.0, 1.0]])


def cameras(count: int = 3) -> torch.Tensor:
    """(count, 4, 4) OpenCV cameras around the origin, looking at it."""
    angles = torch.linspace(0.0, 1.5, count)
    positions = torch.stack([4.0 * torch.cos(angles), 4.0 * torch.sin(angles), 1.0 + angles], dim=-1)
    return look_at(positions, target=torch.zeros(3), up=torch.tensor([0.0, 0.0, 1.0]))


def nerfstudio_path(c2w_opengl: torch.Tensor, fov: float = 50.0, height: int = 60, width: int = 80, **extra) -> dict:
    """A camera_path.json as nerfstudio's viewer exports it."""
    return {"camera_type": "perspective", "render_height": height, "render_width": width, "fps": 24, "seconds": len(c2w_opengl) / 24,
            "keyframes": [], "smoothness_value": 0.5, "is_cycle": False, "crop": None,
            "camera_path": [{"camera_to_world": matrix.flatten().tolist(), "fov": fov, "aspect": width / height} for matrix in c2w_opengl],
            **extra}


def write(path, meta) -> str:
    path.write_text(json.dumps(meta))
    return str(path)


def test_a_nerfstudio_path_is_read_as_ns_render_reads_it(tmp_path):
    capture = opengl_to_opencv(cameras().double())  # OpenGL cameras in the capture's coordinates, as the file has them
    views, fps = read_camera_path(write(tmp_path / "camera_path.json", nerfstudio_path(capture)), WORLD_FROM_CAPTURE)
    assert fps == 24 and (views.height, views.width) == (60, 80) and len(views) == 3
    focal = 0.5 * 60 / math.tan(math.radians(25.0))  # ns-render's three_js_perspective_camera_focal_length
    torch.testing.assert_close(views.K[0], torch.tensor([[focal, 0.0, 40.0], [0.0, focal, 30.0], [0.0, 0.0, 1.0]]))
    # the scene's world: the capture's cameras through WORLD_FROM_CAPTURE, as OpenCV cameras
    centres = (WORLD_FROM_CAPTURE[:3, :3] @ capture[:, :3, 3].float().T).T + WORLD_FROM_CAPTURE[:3, 3]
    torch.testing.assert_close(views.c2w[:, :3, 3], centres, atol=1e-5, rtol=0)
    rotation = WORLD_FROM_CAPTURE[:3, :3] / 0.5
    torch.testing.assert_close(views.c2w[:, :3, :3], rotation @ cameras()[:, :3, :3], atol=1e-5, rtol=0)


def test_a_path_written_is_read_back_and_a_rendered_paths_transforms_json_is_a_path(tmp_path):
    c2w = cameras(4)
    K = torch.tensor([[70.0, 0.0, 40.0], [0.0, 70.0, 30.0], [0.0, 0.0, 1.0]]).repeat(4, 1, 1)
    views = Views(K=K, c2w=c2w, height=60, width=80)
    meta = camera_path_meta(views, WORLD_FROM_CAPTURE, fps=12.0)
    assert meta["seconds"] == pytest.approx(4 / 12) and len(meta["camera_path"]) == 4
    back, fps = read_camera_path(write(tmp_path / "path.json", meta), WORLD_FROM_CAPTURE)
    assert fps == 12.0
    torch.testing.assert_close(back.c2w, c2w, atol=1e-5, rtol=0)
    torch.testing.assert_close(back.K, K, atol=1e-4, rtol=0)
    # nerf-render's own transforms.json of a rendered path (per-frame intrinsics, OpenGL, the capture's coordinates)
    from nerf_lightning.data.formats.transforms import transforms_meta

    rendered = transforms_meta(views, [f"frames/rgb_{index:04d}.png" for index in range(4)], WORLD_FROM_CAPTURE)
    back, fps = read_camera_path(write(tmp_path / "transforms.json", rendered), WORLD_FROM_CAPTURE)
    assert fps is None and (back.height, back.width) == (60, 80)
    torch.testing.assert_close(back.c2w, c2w, atol=1e-5, rtol=0)
    torch.testing.assert_close(back.K, K)


def test_nerfstudios_normalised_world_is_mapped_back_through_its_dataparser_transforms(tmp_path):
    turn = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=torch.float64)
    transform = torch.cat([turn, torch.tensor([[0.5], [-1.0], [2.0]], dtype=torch.float64)], dim=1)  # nerfstudio's 3x4
    scale = 0.25
    (tmp_path / "dataparser_transforms.json").write_text(json.dumps({"transform": transform.tolist(), "scale": scale}))
    capture = opengl_to_opencv(cameras().double())
    nerfstudio_from_capture = torch.eye(4, dtype=torch.float64)
    nerfstudio_from_capture[:3] = scale * transform  # nerfstudio: poses = transform @ poses, then positions * scale
    in_nerfstudio = apply_similarity(nerfstudio_from_capture, capture)
    capture_from_nerfstudio = read_dataparser_transforms(tmp_path / "dataparser_transforms.json")
    torch.testing.assert_close(capture_from_nerfstudio @ nerfstudio_from_capture, torch.eye(4, dtype=torch.float64))
    path = write(tmp_path / "camera_path.json", nerfstudio_path(in_nerfstudio))
    mapped, _ = read_camera_path(path, WORLD_FROM_CAPTURE, tmp_path / "dataparser_transforms.json")
    direct, _ = read_camera_path(write(tmp_path / "direct.json", nerfstudio_path(capture)), WORLD_FROM_CAPTURE)
    torch.testing.assert_close(mapped.c2w, direct.c2w, atol=1e-5, rtol=0)


@pytest.mark.parametrize("meta, expected", [
    ({"cameras": []}, "not a camera path: expected nerfstudio's camera_path.json"),
    ([1, 2], "not a camera path"),
    (nerfstudio_path(torch.eye(4)[None], camera_type="fisheye"), "camera_type 'fisheye': only perspective"),
    (dict(nerfstudio_path(torch.eye(4)[None]), camera_path=[]), "'camera_path' must be a non-empty list"),
    (dict(nerfstudio_path(torch.eye(4)[None]), camera_path=[{"camera_to_world": [1.0] * 16}]), r"camera_path\[0\] has no 'camera_to_world' or no 'fov'"),
    (dict(nerfstudio_path(torch.eye(4)[None]), camera_path=[{"camera_to_world": [float("nan")] + [0.0] * 15, "fov": 50}]),
     "camera_path.json camera_path\\[\\].camera_to_world: camera 0 has non-finite entries"),
    (dict(nerfstudio_path(torch.eye(4)[None]), camera_path=[{"camera_to_world": [1.0] * 12, "fov": 50}]), "must be 16 numbers"),
    (dict(nerfstudio_path(torch.eye(4)[None]), render_height=0), "'render_height' must be a number in"),
    (nerfstudio_path(torch.eye(4)[None], fov=200.0), "'fov' must be a number in \\(0, 180\\)"),
])
def test_a_bad_path_file_is_named_in_one_line(tmp_path, meta, expected):
    path = tmp_path / "camera_path.json"
    path.write_text(json.dumps(meta, allow_nan=True))
    with pytest.raises(ValueError, match=expected) as raised:
        read_camera_path(path)
    assert str(path) in str(raised.value) and "\n" not in str(raised.value)


def test_a_missing_or_unreadable_path_file_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="no such camera path file"):
        read_camera_path(tmp_path / "missing.json")
    (tmp_path / "broken.json").write_text("{not json")
    with pytest.raises(ValueError, match="broken.json: not a camera path: it is not JSON"):
        read_camera_path(tmp_path / "broken.json")
    (tmp_path / "dataparser_transforms.json").write_text(json.dumps({"transform": [[1, 0, 0]], "scale": 1}))
    with pytest.raises(ValueError, match="'transform' must be 3x4"):
        read_dataparser_transforms(tmp_path / "dataparser_transforms.json")


def test_the_keyframe_path_passes_through_its_keyframes_smoothly():
    keyframes = cameras(3)
    fov = torch.tensor([40.0, 50.0, 60.0])
    c2w, fovs = keyframe_path(keyframes, fov, 41)
    # the first and last frames are the first and last keyframes, the middle one the middle keyframe
    for frame, keyframe in ((0, 0), (20, 1), (40, 2)):
        torch.testing.assert_close(c2w[frame], keyframes[keyframe], atol=1e-5, rtol=0)
        assert float(fovs[frame]) == pytest.approx(float(fov[keyframe]))
    rotations = c2w[:, :3, :3].double()
    torch.testing.assert_close(rotations.transpose(1, 2) @ rotations, torch.eye(3, dtype=torch.float64).expand(41, 3, 3), atol=1e-5, rtol=0)
    # smooth: no step between frames much larger than the others, the positions' second differences small
    steps = (c2w[1:, :3, 3] - c2w[:-1, :3, 3]).norm(dim=-1)
    assert steps.max() < 1.6 * steps.mean()
    bends = (c2w[2:, :3, 3] - 2 * c2w[1:-1, :3, 3] + c2w[:-2, :3, 3]).norm(dim=-1)
    assert bends.max() < 0.2 * steps.mean()
    # rotations turn by equal angles within a segment (spherical, not linear, interpolation)
    relative = rotations[1:21].transpose(1, 2) @ rotations[:20]
    angles = torch.acos(((relative.diagonal(dim1=1, dim2=2).sum(-1) - 1) / 2).clamp(-1, 1))
    torch.testing.assert_close(angles, angles.mean().expand(20), atol=1e-4, rtol=0)
    with pytest.raises(ValueError, match="at least two keyframes"):
        keyframe_path(keyframes[:1], fov[:1], 10)


def test_the_viewers_keyframes_save_a_path_that_reads_back_and_refuse_fewer_than_two(tmp_path):
    from nerf_lightning.viz.keyframes import Keyframes

    keyframes = Keyframes(height=60, width=80)
    keyframes.add(cameras(2)[0], 50.0)
    with pytest.raises(ValueError, match="at least two keyframes, the path has 1: add another view"):
        keyframes.camera_path(2.0, 5.0, WORLD_FROM_CAPTURE)
    keyframes.add(cameras(2)[1], 40.0)
    meta = keyframes.camera_path(2.0, 5.0, WORLD_FROM_CAPTURE)
    assert len(meta["camera_path"]) == 10 and len(meta["keyframes"]) == 2 and meta["seconds"] == 2.0
    views, fps = read_camera_path(write(tmp_path / "camera_path.json", meta), WORLD_FROM_CAPTURE)
    assert fps == 5.0 and (views.height, views.width) == (60, 80)
    torch.testing.assert_close(views.c2w[[0, -1]], cameras(2), atol=1e-5, rtol=0)
    fov = torch.rad2deg(2.0 * torch.atan(0.5 * 60 / views.K[[0, -1], 1, 1]))
    torch.testing.assert_close(fov, torch.tensor([50.0, 40.0]), atol=1e-3, rtol=0)
    keyframes.remove(0)
    with pytest.raises(IndexError, match="there is no keyframe 2: the path has 1"):
        keyframes.remove(1)
