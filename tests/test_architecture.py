"""Architecture contracts (issue 19): the import-linter contracts in pyproject.toml hold, a contract broken
on purpose makes ``lint-imports`` fail (so CI would catch it), and no import cycle exists (grimp's graph).

The Warp kernels live in the top-level ``kernels/`` folder and ship as ``codecsplat_warp.kernels``
(pyproject's package-dir mapping), which an editable install maps with an import hook that import-linter's
graph builder does not follow. So both tests lint a copy of the sources in the installed layout
(``codecsplat_warp/`` with ``kernels/`` inside it, and ``train/``) against the repository's pyproject.toml.
By hand: ``lint-imports`` in such a copy (see :func:`_installed_layout`).
"""

from __future__ import annotations

import json
import pathlib
import shutil
import subprocess
import sys

import pytest

pytest.importorskip("importlinter", reason="import-linter (dev extra) is not installed")

ROOT = pathlib.Path(__file__).resolve().parents[1]
_IGNORE = shutil.ignore_patterns("__pycache__", "*.pyc", "assets")


def _installed_layout(dest: pathlib.Path) -> pathlib.Path:
    """Copy the package as it is installed (kernels/ -> codecsplat_warp/kernels/), train/ and pyproject.toml."""
    shutil.copytree(ROOT / "codecsplat_warp", dest / "codecsplat_warp", ignore=_IGNORE)
    shutil.copytree(ROOT / "kernels", dest / "codecsplat_warp" / "kernels", ignore=_IGNORE)
    shutil.copytree(ROOT / "train", dest / "train", ignore=_IGNORE)
    shutil.copy(ROOT / "pyproject.toml", dest / "pyproject.toml")
    return dest


def _lint_imports(cwd: pathlib.Path) -> subprocess.CompletedProcess:
    """``lint-imports --no-cache`` in ``cwd`` (that folder first on the module path)."""
    code = "import sys; from importlinter.cli import lint_imports_command; sys.exit(lint_imports_command())"
    return subprocess.run([sys.executable, "-c", code, "--no-cache"], cwd=cwd, capture_output=True, text=True,
                          env={"PYTHONPATH": str(cwd), "PATH": "/usr/bin:/bin"}, timeout=300)


def test_the_import_contracts_hold(tmp_path):
    result = _lint_imports(_installed_layout(tmp_path))
    assert result.returncode == 0, result.stdout + result.stderr
    assert "0 broken" in result.stdout and " kept" in result.stdout, result.stdout


BREAKS = [
    # (file of the installed layout, import appended to it, contract that must break, chain lint-imports must name)
    ("codecsplat_warp/codec/scene.py", "from ..model import codecsplat",
     "the codec never imports the model, training or the command line",
     "codecsplat_warp.codec.scene -> codecsplat_warp.model"),
    ("codecsplat_warp/kernels/sh.py", "import torch", "the Warp kernels never import torch",
     "codecsplat_warp.kernels.sh -> torch"),
    ("codecsplat_warp/ops/geometry.py", "from ..bench import report",
     "the core never imports the benchmarks, training or the command line",
     "codecsplat_warp.ops.geometry -> codecsplat_warp.bench.report"),
]


@pytest.mark.parametrize("file,line,contract,chain", BREAKS, ids=["codec->model", "kernels->torch", "ops->bench"])
def test_a_contract_broken_on_purpose_fails(tmp_path, file, line, contract, chain):
    """One import that points up (the codec importing the model is the loop issue 19 removed) makes
    ``lint-imports`` exit non-zero, naming the contract and the import; the layers contract breaks too."""
    tree = _installed_layout(tmp_path)
    module = tree / file
    module.write_text(module.read_text() + f"\n{line}  # noqa: E402,F401  broken on purpose\n")
    result = _lint_imports(tree)
    assert result.returncode != 0, result.stdout
    assert f"{contract} BROKEN" in result.stdout and chain in result.stdout, result.stdout
    if not chain.endswith("torch"):
        assert "layers only point down BROKEN" in result.stdout, result.stdout


def _import_cycles(tree: pathlib.Path) -> list[tuple[str, str]]:
    """Pairs (a, b) of the package's modules where a imports b and b reaches a back through imports, counting
    imports inside functions too (a lazy import that exists to dodge a cycle is still a cycle)."""
    code = ("import grimp, json; g = grimp.build_graph('codecsplat_warp', 'train', cache_dir=None); "
            "print(json.dumps(sorted({tuple(sorted((a, b))) for a in g.modules "
            "for b in g.find_modules_directly_imported_by(a) if g.find_shortest_chain(importer=b, imported=a)})))")
    result = subprocess.run([sys.executable, "-c", code], cwd=tree, capture_output=True, text=True,
                            env={"PYTHONPATH": str(tree), "PATH": "/usr/bin:/bin"}, timeout=300)
    assert result.returncode == 0, result.stderr
    return [tuple(pair) for pair in json.loads(result.stdout)]


def test_no_import_cycles(tmp_path):
    """No cycle anywhere in the package; the lazy import data/dataset.py used to make (``from . import
    load_scene`` inside a method, against ``data/__init__`` importing dataset) is found if put back."""
    tree = _installed_layout(tmp_path)
    assert _import_cycles(tree) == []
    dataset = tree / "codecsplat_warp" / "data" / "dataset.py"
    dataset.write_text(dataset.read_text() + "\n\ndef _lazy():\n    from . import load_scene  # noqa: F401\n")
    assert _import_cycles(tree) == [("codecsplat_warp.data", "codecsplat_warp.data.dataset")]
