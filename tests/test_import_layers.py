"""The packages' import layers and cycles ([tool.importlinter] in pyproject.toml), checked by import-linter.

import-linter reads the sources statically; it finds each root package through PYTHONPATH, set here to the
packages' source folders (pytest's own pythonpath), so the check sees the working tree, not the install tree.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())
ROOT_PACKAGES: list[str] = PYPROJECT["tool"]["importlinter"]["root_packages"]
CONTRACTS = {c["id"]: c for c in PYPROJECT["tool"]["importlinter"]["contracts"]}


def package_folders(root: Path) -> dict[str, Path]:
    """Each root package's source folder under ``root`` (one of pytest's pythonpath entries)."""
    folders = [root / p for p in PYPROJECT["tool"]["pytest"]["ini_options"]["pythonpath"]]
    found = {pkg: f for f in folders for pkg in ROOT_PACKAGES if (f / pkg / "__init__.py").is_file()}
    assert set(found) == set(ROOT_PACKAGES), f"no source folder for {set(ROOT_PACKAGES) - set(found)}"
    return found


def lint_imports(root: Path) -> subprocess.CompletedProcess[str]:
    """``lint-imports`` over the packages under ``root`` with ``root/pyproject.toml``'s contracts."""
    exe = shutil.which("lint-imports", path=str(Path(sys.executable).parent)) or shutil.which("lint-imports")
    assert exe, "lint-imports not found: requirements/main.txt installs import-linter (make setup)"
    path = os.pathsep.join(sorted({str(f) for f in package_folders(root).values()}))
    env = dict(os.environ, PYTHONPATH=path, COLUMNS="200")  # wide: a contract's name stays on one line
    return subprocess.run([exe, "--no-cache", "--config", str(root / "pyproject.toml")], cwd=root, env=env,
                          capture_output=True, text=True, timeout=60)


def test_the_packages_keep_their_import_contracts():
    done = lint_imports(REPO)
    assert done.returncode == 0, done.stdout + done.stderr
    for contract in CONTRACTS.values():
        assert f"{contract['name']} KEPT" in done.stdout


def test_an_upward_import_breaks_the_layers_contract(tmp_path: Path):
    # the same packages and contracts in a scratch tree, with the core importing the bringup package
    for pkg, folder in package_folders(REPO).items():
        shutil.copytree(folder / pkg, tmp_path / folder.relative_to(REPO) / pkg,
                        ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(REPO / "pyproject.toml", tmp_path / "pyproject.toml")
    topics = tmp_path / package_folders(tmp_path)["nf_core"].relative_to(tmp_path) / "nf_core" / "topics.py"
    topics.write_text(topics.read_text() + "\nimport nf_bringup  # noqa: E402\n")

    done = lint_imports(tmp_path)
    assert done.returncode != 0, done.stdout + done.stderr
    assert f"{CONTRACTS['layers']['name']} BROKEN" in done.stdout, done.stdout
    assert "nf_core is not allowed to import nf_bringup" in done.stdout, done.stdout
    assert "nf_core.topics -> nf_bringup" in done.stdout, done.stdout
