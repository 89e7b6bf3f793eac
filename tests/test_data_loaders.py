"""Scene loaders on the real scenes (CODECSPLAT_DATA) and on hand-made bad inputs."""

from __future__ import annotations

import json
import pathlib
import struct

import numpy as np
import pytest
import torch
from PIL import Image

from codecsplat_warp.data import (FORMATS, detect_formats, load_7scenes, load_colmap, load_kitti, load_llff,
                                  load_middlebury, load_nerf, load_neus, load_scene, load_scene_json, load_strecha)
from codecsplat_warp.data.colmap import CAMERA_MODELS, read_model
from codecsplat_warp.errors import DataError

C2W_TOLERANCE = 1e-4
INTRINSICS_RELATIVE_TOLERANCE = 1e-3
NATIVE_LOADERS = {"llff": load_llff, "nerf": load_nerf, "neus": load_neus, "middlebury": load_middlebury,
                  "colmap": load_colmap, "kitti": load_kitti, "7scenes": load_7scenes, "strecha": load_strecha}


def _scene_dirs(root: pathlib.Path) -> list[pathlib.Path]:
    dirs = sorted(p for p in root.iterdir() if p.is_dir())
    assert dirs, f"no scene folders in {root}"
    return dirs


def _reference_cameras(scene_dir: pathlib.Path) -> dict[str, dict]:
    """cameras.json read with plain json/numpy (independent of the package), by frame file."""
    data = json.loads((scene_dir / "cameras.json").read_text())
    return {f["file"]: f for f in data["frames"]}


def _assert_same_cameras(scene, reference: dict[str, dict], what: str) -> None:
    assert sorted(scene.frame_names) == sorted(reference), f"{what}: frame sets differ"
    c2w = scene.cameras.c2w.numpy()
    K = scene.cameras.K.numpy()
    for v, name in enumerate(scene.frame_names):
        ref = reference[name]
        assert np.abs(c2w[v] - np.array(ref["c2w"])).max() < C2W_TOLERANCE, f"{what}: {name} c2w"
        got = np.array([K[v, 0, 0], K[v, 1, 1], K[v, 0, 2], K[v, 1, 2]])
        want = np.array([ref["fx"], ref["fy"], ref["cx"], ref["cy"]])
        assert np.abs(got / want - 1).max() < INTRINSICS_RELATIVE_TOLERANCE, f"{what}: {name} intrinsics {got} vs {want}"
        assert (scene.cameras.width, scene.cameras.height) == (ref["w"], ref["h"]), f"{what}: {name} size"


@pytest.mark.data
def test_every_scene_native_and_json_agree(data_root):
    for scene_dir in _scene_dirs(data_root):
        reference = _reference_cameras(scene_dir)
        from_json = load_scene(scene_dir)
        assert from_json.source.startswith("scene-json:")
        _assert_same_cameras(from_json, reference, f"{scene_dir.name} cameras.json")
        formats = detect_formats(scene_dir)
        native = [f for f in formats if f != "scene-json"]
        assert len(native) == 1, f"{scene_dir.name}: expected one native pose file, found {native}"
        scene = load_scene(scene_dir, prefer_native=True)
        assert scene.source.startswith(native[0] + ":")
        _assert_same_cameras(scene, reference, f"{scene_dir.name} {native[0]}")
        direct = NATIVE_LOADERS[native[0]](formats[native[0]])
        assert torch.equal(direct.cameras.w2c, scene.cameras.w2c)
        assert direct.frame_names == from_json.frame_names, f"{scene_dir.name}: frame order differs from cameras.json"


@pytest.mark.data
def test_depth_bounds_where_the_format_has_them(data_root):
    """LLFF and NeuS loaders reproduce cameras.json near/far (llff_bounds and unit_sphere rules)."""
    for scene_dir in _scene_dirs(data_root):
        formats = detect_formats(scene_dir)
        if not {"llff", "neus"} & set(formats):
            continue
        data = json.loads((scene_dir / "cameras.json").read_text())
        scene = load_scene(scene_dir, prefer_native=True)
        np.testing.assert_allclose(scene.cameras.near.numpy(), data["near"], rtol=1e-6, err_msg=scene_dir.name)
        np.testing.assert_allclose(scene.cameras.far.numpy(), data["far"], rtol=1e-6, err_msg=scene_dir.name)


@pytest.mark.data
def test_images_decode_at_camera_size(data_root):
    for scene_dir in _scene_dirs(data_root):
        scene = load_scene(scene_dir, prefer_native=True)
        first_last = scene.decoded_images([0, scene.num_views - 1])
        assert first_last.dtype == torch.uint8
        assert first_last.shape == (2, 3, scene.cameras.height, scene.cameras.width)
        reference = np.asarray(Image.open(scene_dir / scene.frame_names[0]).convert("RGB"))
        assert np.array_equal(first_last[0].permute(1, 2, 0).numpy(), reference)


@pytest.mark.data
def test_load_scene_accepts_pose_files(data_root):
    for scene_dir, file in ((data_root / "cap_beer", "poses_bounds.npy"), (data_root / "cap_gum", "transforms_train.json"),
                            (data_root / "dtu_scan37", "cameras_sphere.npz"), (data_root / "middlebury_dino", "dino_par.txt"),
                            (data_root / "other_kitti00", "poses.txt"),
                            (data_root / "other_7scenes_redkitchen", "camera-intrinsics.txt"),
                            (data_root / "other_dancer", "transforms.json"), (data_root / "llff_room", "cameras.json"),
                            (data_root / "strecha_entry_p10", "gt_dense_cameras")):
        scene = load_scene(scene_dir / file)
        assert scene.key == scene_dir.name and scene.num_views == len(_reference_cameras(scene_dir))
    scene = load_scene(data_root / "llff_room" / "sparse" / "0")
    assert scene.source.startswith("colmap:") and scene.key == "llff_room"


# --------------------------------------------------------------------------------------------------
# COLMAP binary: written here from a parsed text model, read back by the package
def _write_colmap_binary(model, folder: pathlib.Path) -> None:
    model_ids = {name: model_id for model_id, (name, _) in CAMERA_MODELS.items()}
    with open(folder / "cameras.bin", "wb") as f:
        f.write(struct.pack("<Q", len(model.cameras)))
        for camera_id, cam in model.cameras.items():
            f.write(struct.pack("<iiQQ", camera_id, model_ids[cam.model], cam.width, cam.height))
            f.write(struct.pack(f"<{len(cam.params)}d", *cam.params))
    with open(folder / "images.bin", "wb") as f:
        f.write(struct.pack("<Q", len(model.images)))
        for im in model.images:
            f.write(struct.pack("<i7di", im.image_id, *im.qvec, *im.tvec, im.camera_id))
            f.write(im.name.encode() + b"\x00")
            f.write(struct.pack("<Q", len(im.point3d_ids)))
            for k, pid in enumerate(im.point3d_ids):
                f.write(struct.pack("<ddq", 10.0 + k, 20.0 + k, int(pid)))
    with open(folder / "points3D.bin", "wb") as f:
        f.write(struct.pack("<Q", len(model.points)))
        for pid, xyz in model.points.items():
            f.write(struct.pack("<Q3d3BdQ", pid, *xyz, 1, 2, 3, 0.5, 1))
            f.write(struct.pack("<ii", 1, 0))


def _add_points(model, count: int, seed: int = 0) -> None:
    """Points in front of the first camera, observed by every image (so near/far come from them)."""
    rng = np.random.default_rng(seed)
    c2w0 = np.linalg.inv(_w2c_of(model.images[0]))
    for pid in range(1, count + 1):
        cam_point = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(5.0, 50.0), 1.0])
        model.points[pid] = (c2w0 @ cam_point)[:3]
    for im in model.images:
        im.point3d_ids = np.arange(1, count + 1)


def _w2c_of(image) -> np.ndarray:
    w, x, y, z = image.qvec / np.linalg.norm(image.qvec)
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                  [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                  [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, image.tvec
    return T


@pytest.mark.data
def test_colmap_binary_matches_text(data_root, tmp_path):
    scene_dir = tmp_path / "llff_room"
    (scene_dir / "sparse" / "0").mkdir(parents=True)
    (scene_dir / "images").symlink_to(data_root / "llff_room" / "images")
    model = read_model(data_root / "llff_room" / "sparse" / "0")
    _add_points(model, 50)
    _write_colmap_binary(model, scene_dir / "sparse" / "0")
    binary = load_scene(scene_dir)
    assert binary.source.startswith("colmap:")
    _assert_same_cameras(binary, _reference_cameras(data_root / "llff_room"), "binary COLMAP")
    depths = np.concatenate([(_w2c_of(im) @ np.c_[np.stack(list(model.points.values())), np.ones(50)].T)[2]
                             for im in model.images])
    assert depths.min() > 0
    assert 0.9 * depths.min() <= float(binary.cameras.near[0]) <= 0.9 * np.percentile(depths, 50)
    assert 1.1 * np.percentile(depths, 50) <= float(binary.cameras.far[0]) <= 1.1 * depths.max()
    text = load_colmap(data_root / "llff_room" / "sparse" / "0")
    assert torch.allclose(text.cameras.w2c, binary.cameras.w2c, atol=1e-12)


# --------------------------------------------------------------------------------------------------
# Bad input
def _tiny_jpegs(folder: pathlib.Path, names, size=(8, 6)) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        Image.new("RGB", size, (120, 30, 200)).save(folder / name)


def _scene_json(folder: pathlib.Path, frames: int = 3, **overrides) -> pathlib.Path:
    _tiny_jpegs(folder / "images", [f"{i}.jpg" for i in range(frames)])
    data = {"format": "codecsplat-scene-v1", "near": 0.5, "far": 10.0,
            "frames": [{"file": f"images/{i}.jpg", "w": 8, "h": 6, "fx": 7.0, "fy": 7.0, "cx": 4.0, "cy": 3.0,
                        "c2w": np.eye(4).tolist()} for i in range(frames)]}
    data.update(overrides)
    (folder / "cameras.json").write_text(json.dumps(data))
    return folder / "cameras.json"


def test_valid_tiny_scene_loads(tmp_path):
    scene = load_scene(_scene_json(tmp_path).parent)
    assert scene.decoded_images().shape == (3, 3, 6, 8)


@pytest.mark.parametrize("case, expected", [
    ("nan_pose", r"cameras\.json: frame 2"),
    ("bad_rotation", r"cameras\.json: view 1: w2c rotation"),
    ("missing_key", r"cameras\.json: frame 0 lacks fx"),
    ("mixed_sizes", r"cameras\.json: frame 1 is 9x6"),
    ("bad_json", r"cameras\.json: not valid JSON"),
    ("wrong_format", r"cameras\.json: format is 'other'"),
])
def test_scene_json_errors(tmp_path, case, expected):
    file = _scene_json(tmp_path)
    data = json.loads(file.read_text())
    if case == "nan_pose":
        data["frames"][2]["c2w"][0][3] = float("nan")
    elif case == "bad_rotation":
        data["frames"][1]["c2w"][0][0] = 2.0
    elif case == "missing_key":
        del data["frames"][0]["fx"]
    elif case == "mixed_sizes":
        data["frames"][1]["w"] = 9
    elif case == "wrong_format":
        data["format"] = "other"
    file.write_text("{not json" if case == "bad_json" else json.dumps(data))
    with pytest.raises(DataError, match=expected):
        load_scene_json(file)


def test_image_size_mismatch_names_file_and_frame(tmp_path):
    file = _scene_json(tmp_path)
    Image.new("RGB", (5, 5)).save(tmp_path / "images" / "1.jpg")
    scene = load_scene(file)
    with pytest.raises(DataError, match=r"frame 1: image .*1\.jpg is 5x5, the cameras say 8x6"):
        scene.decoded_images()


def test_missing_image_names_file_and_frame(tmp_path):
    file = _scene_json(tmp_path)
    (tmp_path / "images" / "2.jpg").unlink()
    with pytest.raises(DataError, match=r"frame 2: image file .*2\.jpg does not exist"):
        load_scene(file).decoded_images([2])


def _llff(folder: pathlib.Path, rows: int, images: int) -> pathlib.Path:
    _tiny_jpegs(folder / "images", [f"{i}.jpg" for i in range(images)])
    matrix = np.zeros((rows, 3, 5))
    matrix[:, :, :3] = [[0, 1, 0], [1, 0, 0], [0, 0, -1]]  # columns: down, right, backward
    matrix[:, :, 4] = [6, 8, 7]
    array = np.concatenate([matrix.reshape(rows, 15), np.tile([1.0, 5.0], (rows, 1))], axis=1)
    np.save(folder / "poses_bounds.npy", array)
    return folder / "poses_bounds.npy"


def test_llff_errors(tmp_path):
    good = load_llff(_llff(tmp_path / "good", 2, 2))
    assert torch.allclose(good.cameras.w2c[0], torch.eye(4, dtype=torch.float64))
    assert float(good.cameras.near[0]) == pytest.approx(0.9) and float(good.cameras.far[0]) == pytest.approx(5.5)
    with pytest.raises(DataError, match=r"poses_bounds\.npy: 3 pose rows but 2 images"):
        load_llff(_llff(tmp_path / "count", 3, 2))
    file = _llff(tmp_path / "nan", 2, 2)
    array = np.load(file)
    array[1, 3] = np.inf
    np.save(file, array)
    with pytest.raises(DataError, match=r"poses_bounds\.npy: frame 1: row \(images/1\.jpg\) holds NaN or Inf"):
        load_llff(file)
    np.save(file, array[:, :14])
    with pytest.raises(DataError, match=r"expected an \[N,17\] LLFF array"):
        load_llff(file)


def test_nerf_errors(tmp_path):
    _tiny_jpegs(tmp_path / "images", ["a.jpg", "b.jpg"])
    frames = [{"file_path": "images/a.jpg", "transform_matrix": np.eye(4).tolist()}, {"file_path": "images/b.jpg"}]
    file = tmp_path / "transforms.json"
    file.write_text(json.dumps({"camera_angle_x": 1.0, "frames": frames}))
    with pytest.raises(DataError, match=r"transforms\.json: frame 1 \(images/b\.jpg\) lacks 'transform_matrix'"):
        load_nerf(file)
    frames[1]["transform_matrix"] = np.eye(4).tolist()
    file.write_text(json.dumps({"camera_angle_x": 1.0, "frames": frames}))
    scene = load_nerf(file, near=0.1, far=3.0)
    assert scene.cameras.K[0, 0, 0].item() == pytest.approx(0.5 * 8 / np.tan(0.5))
    assert torch.allclose(scene.cameras.c2w[0], torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64)))


def test_nerf_per_frame_matrix(tmp_path):
    """A per-frame 3x3 ``K`` (other_dancer's layout) gives that frame's fx, fy, cx, cy; explicit keys win over it."""
    _tiny_jpegs(tmp_path / "images", ["a.jpg", "b.jpg"])
    K = [[[7.0, 0, 4.1], [0, 6.5, 2.9], [0, 0, 1]], [[7.5, 0, 3.9], [0, 7.2, 3.1], [0, 0, 1]]]
    frames = [{"file_path": f"images/{n}.jpg", "transform_matrix": np.eye(4).tolist(), "K": k} for n, k in zip("ab", K)]
    frames[1]["cx"] = 4.0
    file = tmp_path / "transforms.json"
    file.write_text(json.dumps({"w": 8, "h": 6, "frames": frames}))
    scene = load_nerf(file, near=0.1, far=3.0)
    np.testing.assert_array_equal(scene.cameras.K[0].numpy(), K[0])
    np.testing.assert_array_equal(scene.cameras.K[1].numpy(), [[7.5, 0, 4.0], [0, 7.2, 3.1], [0, 0, 1]])
    file.write_text(json.dumps({"w": 8, "h": 6, "K": K[0], "frames": [{k: v for k, v in f.items() if k != "K"}
                                                                      for f in frames]}))
    assert load_nerf(file, near=0.1, far=3.0).cameras.K[0, 0, 0].item() == 7.0  # a top-level K serves every frame
    for bad, expected in ((K[0][:2], r"'K' must be 3x3, got shape \(2, 3\)"), ([[7, 0, "x"]] * 3, r"'K' must be a 3x3 matrix"),
                          ([[7, 0.5, 4], [0, 7, 3], [0, 0, 1]], r"'K' must be a pinhole matrix"),
                          ([[7, 0, 4], [0, float("nan"), 3], [0, 0, 1]], r"'K' holds NaN or Inf")):
        frames[1]["K"] = bad
        file.write_text(json.dumps({"w": 8, "h": 6, "frames": frames}))
        with pytest.raises(DataError, match=r"transforms\.json: frame 1 \(images/b\.jpg\): " + expected):
            load_nerf(file)


def _kitti(folder: pathlib.Path, poses: int, images: int, p0: str = "7 0 3.5 0 0 6.5 2.5 0 0 0 1 0") -> pathlib.Path:
    _tiny_jpegs(folder / "images", [f"{i:06d}.jpg" for i in range(images)])
    (folder / "images.txt").write_text("".join(f"images/{i:06d}.jpg\n" for i in range(images)))
    (folder / "calib.txt").write_text(f"P0: {p0}\nP1: 7 0 3.5 -3.8 0 6.5 2.5 0 0 0 1 0\n")
    lines = [" ".join(str(v) for v in np.c_[np.eye(3), [0, 0, float(i)]].ravel()) for i in range(poses)]
    (folder / "poses.txt").write_text("\n".join(lines) + "\n")
    return folder / "poses.txt"


def test_kitti_loader_and_errors(tmp_path):
    """KITTI poses.txt rows are c2w (OpenCV axes); calib.txt P0 gives K with integer pixel centres (+0.5 here)."""
    file = _kitti(tmp_path / "good", 3, 3)
    assert list(detect_formats(file.parent)) == ["kitti"] and load_scene(file).source.startswith("kitti:")
    scene = load_kitti(file, near=0.5, far=20.0)
    assert scene.frame_names == ["images/000000.jpg", "images/000001.jpg", "images/000002.jpg"]
    np.testing.assert_array_equal(scene.cameras.K[0].numpy(), [[7, 0, 4.0], [0, 6.5, 3.0], [0, 0, 1]])
    np.testing.assert_array_equal(scene.cameras.c2w[2, :3, 3].numpy(), [0, 0, 2])
    (file.parent / "images.txt").unlink()  # then images/ in natural order
    assert load_kitti(file).frame_names == scene.frame_names
    with pytest.raises(DataError, match=r"poses\.txt: 4 pose lines but 3 images"):
        load_kitti(_kitti(tmp_path / "count", 4, 3))
    with pytest.raises(DataError, match=r"calib\.txt: P0 must be \[\[fx, 0, cx, 0\]"):
        load_kitti(_kitti(tmp_path / "p0", 2, 2, p0="7 0 3.5 -3.8 0 6.5 2.5 0 0 0 1 0"))
    with pytest.raises(DataError, match=r"calib\.txt: P0: expected 12 numbers"):
        load_kitti(_kitti(tmp_path / "short", 2, 2, p0="7 0 3.5 0"))
    file = _kitti(tmp_path / "nan", 2, 2)
    file.write_text(file.read_text().replace("1.0", "nan", 1))
    with pytest.raises(DataError, match=r"poses\.txt: frame 0: pose holds NaN or Inf"):
        load_kitti(file)
    file.write_text("1 0 0 0\n")
    with pytest.raises(DataError, match=r"poses\.txt: frame 0: expected 12 numbers"):
        load_kitti(file)


def _seven_scenes(folder: pathlib.Path, frames: int) -> pathlib.Path:
    _tiny_jpegs(folder / "images", [f"frame-{i:06d}.color.jpg" for i in range(frames)])
    (folder / "poses").mkdir()
    for i in range(frames):
        c2w = np.eye(4)
        c2w[0, 3] = 0.1 * i
        np.savetxt(folder / "poses" / f"frame-{i:06d}.pose.txt", c2w)
    np.savetxt(folder / "camera-intrinsics.txt", [[7.0, 0, 4.0], [0, 6.5, 3.0], [0, 0, 1]])
    return folder / "camera-intrinsics.txt"


def test_7scenes_loader_and_errors(tmp_path):
    """7-Scenes camera-intrinsics.txt (pixels, used as is) + one 4x4 c2w per poses/<frame>.pose.txt."""
    file = _seven_scenes(tmp_path / "good", 3)
    assert list(detect_formats(file.parent)) == ["7scenes"] and load_scene(file).source.startswith("7scenes:")
    scene = load_7scenes(file, near=0.5, far=20.0)
    assert scene.frame_names == [f"images/frame-{i:06d}.color.jpg" for i in range(3)]
    np.testing.assert_array_equal(scene.cameras.K[0].numpy(), [[7.0, 0, 4.0], [0, 6.5, 3.0], [0, 0, 1]])
    np.testing.assert_allclose(scene.cameras.c2w[2, 0, 3].item(), 0.2)
    (file.parent / "images" / "frame-000001.color.jpg").unlink()
    with pytest.raises(DataError, match=r"frame-000001\.pose\.txt: frame 1: no colour image frame-000001\.color\.\*"):
        load_7scenes(file)
    file = _seven_scenes(tmp_path / "pose", 2)
    (file.parent / "poses" / "frame-000001.pose.txt").write_text("1 0 0 0\n0 1 0 0\n0 0 1 0\n")
    with pytest.raises(DataError, match=r"frame-000001\.pose\.txt: frame 1: expected 4 rows of 4 numbers, got 3 rows"):
        load_7scenes(file)
    file.write_text("7 0 4\n0 6.5 3\n0 0 2\n")
    with pytest.raises(DataError, match=r"camera-intrinsics\.txt: expected a pinhole matrix"):
        load_7scenes(file)


def _strecha(folder: pathlib.Path, frames: int) -> pathlib.Path:
    """A Strecha scene of ``frames`` views: camera k at C = (k, 0, -5) turned 90 degrees about the world z axis."""
    names = [f"{i:04d}.jpg" for i in range(frames)]
    _tiny_jpegs(folder / "images", names)
    (folder / "gt_dense_cameras").mkdir()
    R = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]  # columns: camera x, y, z axes in world coordinates
    for i, name in enumerate(names):
        lines = [[7.0, 0, 4.0], [0, 6.5, 3.0], [0, 0, 1], [0.1, 0, 0], *R, [float(i), 0, -5.0], [8, 6]]
        text = "".join(" ".join(str(v) for v in line) + " \n" for line in lines)
        (folder / "gt_dense_cameras" / f"{name}.camera").write_text(text)
    return folder / "gt_dense_cameras"


def test_strecha_loader(tmp_path):
    """Strecha .camera files: K, distortion (kept aside), R camera-to-world (OpenCV axes), camera centre, w h."""
    cameras = _strecha(tmp_path / "scene", 12)
    assert list(detect_formats(cameras.parent)) == ["strecha"] and load_scene(cameras.parent).source.startswith("strecha:")
    scene = load_strecha(cameras, near=0.5, far=20.0)
    assert scene.key == "scene" and scene.frame_names == [f"images/{i:04d}.jpg" for i in range(12)]
    np.testing.assert_array_equal(scene.cameras.K[3].numpy(), [[7.0, 0, 4.0], [0, 6.5, 3.0], [0, 0, 1]])
    np.testing.assert_array_equal(scene.cameras.c2w[3].numpy(), [[0, -1, 0, 3], [1, 0, 0, 0], [0, 0, 1, -5], [0, 0, 0, 1]])
    assert scene.metadata["distortion"][0] == [0.1, 0, 0]
    assert (scene.cameras.width, scene.cameras.height) == (8, 6) and scene.decoded_images([11]).shape == (1, 3, 6, 8)
    (cameras / "0002.jpg.camera").rename(cameras / "2.jpg.camera")  # natural order: 2 between 0001 and 0003
    assert load_strecha(cameras).frame_names[1:4] == ["images/0001.jpg", "images/2.jpg", "images/0003.jpg"]


@pytest.mark.parametrize("case, expected", [
    ("short", r"0001\.jpg\.camera: expected 9 lines \(K, distortion, R, camera centre, w h\), got 8"),
    ("count", r"0001\.jpg\.camera: line 8 \(camera centre\): expected 3 numbers, got 2 fields"),
    ("text", r"0001\.jpg\.camera: line 6 \(R\): not a number in \['1', 'x', '0'\]"),
    ("nan", r"0001\.jpg\.camera: line 4 \(distortion\): holds NaN or Inf"),
    ("skew", r"0001\.jpg\.camera: lines 1-3 \(K\): expected a pinhole matrix"),
    ("size", r"0001\.jpg\.camera: line 9 \(w h\): expected two positive whole numbers, got \[8\.5, 6\.0\]"),
    ("mixed", r"gt_dense_cameras: frame 1 is 9x6 but frame 0 is 8x6"),
    ("rotation", r"gt_dense_cameras: view 1: w2c rotation is not a proper orthonormal rotation"),
    ("empty", r"gt_dense_cameras: no \*\.camera file"),
])
def test_strecha_errors(tmp_path, case, expected):
    cameras = _strecha(tmp_path / "scene", 2)
    file = cameras / "0001.jpg.camera"
    lines = file.read_text().splitlines()
    edits = {"short": (8, None), "count": (7, "1 0"), "text": (5, "1 x 0"), "nan": (3, "0 nan 0"),
             "skew": (0, "7 0.5 4"), "size": (8, "8.5 6"), "mixed": (8, "9 6"), "rotation": (4, "0 -2 0")}
    if case == "empty":
        for camera_file in cameras.iterdir():
            camera_file.unlink()
    elif edits[case][1] is None:
        file.write_text("\n".join(lines[:edits[case][0]]))
    else:
        lines[edits[case][0]] = edits[case][1]
        file.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=expected):
        load_strecha(cameras)


def test_middlebury_and_neus_errors(tmp_path):
    _tiny_jpegs(tmp_path / "images", ["v0.png"])
    par = tmp_path / "x_par.txt"
    line = "v0.png 7 0 4 0 7 3 0 0 1 1 0 0 0 1 0 0 0 1 0 0 2"
    par.write_text(f"2\n{line}\n")
    with pytest.raises(DataError, match=r"x_par\.txt: header says 2 views but 1 view lines follow"):
        load_middlebury(par)
    par.write_text(f"1\n{line.replace(' 2', ' nan')}\n")
    with pytest.raises(DataError, match=r"x_par\.txt: frame 0: \(v0\.png\) K/R/t holds NaN or Inf"):
        load_middlebury(par)
    np.savez(tmp_path / "cameras_sphere.npz", world_mat_0=np.eye(4), world_mat_1=np.eye(4))
    with pytest.raises(DataError, match=r"cameras_sphere\.npz: 2 world_mat_i matrices but 1 images"):
        load_neus(tmp_path / "cameras_sphere.npz")


def test_neus_decomposition_recovers_camera(tmp_path):
    _tiny_jpegs(tmp_path / "images", ["0.png"])
    angle = 0.3
    R = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    K = np.array([[7.0, 0, 4.0], [0, 6.5, 3.0], [0, 0, 1]])
    t = np.array([0.1, -0.2, 3.0])
    world = np.eye(4)
    world[:3] = -2.5 * K @ np.c_[R, t]  # P is defined up to scale and sign
    np.savez(tmp_path / "cameras_sphere.npz", world_mat_0=world, scale_mat_0=np.eye(4))
    scene = load_neus(tmp_path / "cameras_sphere.npz")
    np.testing.assert_allclose(scene.cameras.K[0].numpy(), K, atol=1e-12)
    np.testing.assert_allclose(scene.cameras.w2c[0, :3].numpy(), np.c_[R, t], atol=1e-12)


@pytest.mark.data
def test_colmap_errors(tmp_path, data_root):
    folder = tmp_path / "sparse"
    folder.mkdir()
    (folder / "cameras.txt").write_text("1 OPENCV_FISHEYE 8 6 7 7 4 3 0 0 0 0\n")
    (folder / "images.txt").write_text("1 1 0 0 0 0 0 0 1 a.jpg\n\n")
    (tmp_path / "images").mkdir()
    with pytest.raises(DataError, match=r"frame 0 \(a\.jpg\): camera model OPENCV_FISHEYE is not supported"):
        load_colmap(folder)
    (folder / "images.txt").write_text("1 1 0 0 0 0 0 0 2 a.jpg\n\n")
    with pytest.raises(DataError, match=r"frame 0 \(a\.jpg\) uses camera 2, which is not defined"):
        load_colmap(folder)
    binary = tmp_path / "binary"
    binary.mkdir()
    model = read_model(data_root / "llff_room" / "sparse" / "0")
    _write_colmap_binary(model, binary)
    (binary / "images.bin").write_bytes((binary / "images.bin").read_bytes()[:100])
    with pytest.raises(DataError, match=r"images\.bin: truncated"):
        read_model(binary)


def test_detection_errors(tmp_path):
    with pytest.raises(DataError, match="does not exist"):
        load_scene(tmp_path / "missing")
    with pytest.raises(DataError, match="no supported pose file"):
        load_scene(tmp_path)
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(DataError, match=r"notes\.txt: unsupported pose file"):
        load_scene(tmp_path / "notes.txt")
    with pytest.raises(DataError, match="unknown scene format 'ply'"):
        load_scene(tmp_path, format="ply")
    assert set(FORMATS) == {"scene-json", *NATIVE_LOADERS}
