"""The built wheel ships the kernels as ``codecsplat_warp.kernels`` and imports in a fresh venv."""

from __future__ import annotations

import pathlib
import site
import subprocess
import sys
import sysconfig
import zipfile

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _build_wheel(out: pathlib.Path) -> pathlib.Path:
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(out), str(ROOT)],
                   check=True, capture_output=True)
    (wheel,) = out.glob("codecsplat_warp-*.whl")
    return wheel


def test_wheel_installs_in_fresh_venv_and_imports_kernels(tmp_path):
    wheel = _build_wheel(tmp_path / "dist")
    names = zipfile.ZipFile(wheel).namelist()
    assert "codecsplat_warp/kernels/reproject.py" in names
    assert not any(n.startswith("kernels/") for n in names), "no top-level kernels package may ship"
    assert "codecsplat_warp/assets/codecsplat-default.safetensors" in names, "the shipped model must be in the wheel"
    demo_scene = ROOT / "codecsplat_warp" / "assets" / "scenes" / "nerd_mary_rose"
    for file in [demo_scene / "cameras.json", *sorted((demo_scene / "images").iterdir())]:  # codecsplat demo's scene
        assert file.relative_to(ROOT).as_posix() in names, f"{file.name} of the demo scene is missing from the wheel"
    for init in (ROOT / "codecsplat_warp").rglob("__init__.py"):
        assert init.relative_to(ROOT).as_posix() in names, f"{init.parent.name} is missing from pyproject's packages"

    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    py = venv / "bin" / "python"
    fresh_site = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                                check=True, capture_output=True, text=True).stdout.strip()
    # torch, warp and friends come from this interpreter's site-packages (offline install, --no-deps)
    deps = [sysconfig.get_paths()["purelib"], *site.getsitepackages()]
    pathlib.Path(fresh_site, "host_deps.pth").write_text("\n".join(dict.fromkeys(deps)) + "\n")
    subprocess.run([str(py), "-m", "pip", "install", "--no-deps", "--no-index", "-q", str(wheel)], check=True,
                   capture_output=True)
    probe = (
        "import importlib.util, torch, codecsplat_warp.kernels as k;"
        "from codecsplat_warp.ops.geometry import unproject;"
        "from codecsplat_warp.synthetic import make_rig, smooth_depth;"
        "print(k.__file__);"
        "print(importlib.util.find_spec('kernels'));"
        "print(float(unproject(smooth_depth(1, 2, 3), make_rig(1, 3, 2))[..., 2].min()) > 0)"
    )
    out = subprocess.run([str(py), "-c", probe], check=True, capture_output=True, text=True, cwd=tmp_path).stdout.split()
    assert out[0].startswith(str(venv)), f"kernels imported from {out[0]}, not from the installed wheel"
    assert out[1] == "None", "a top-level `kernels` module must not be importable"
    assert out[2] == "True"
    assert (venv / "bin" / "codecsplat").exists()
