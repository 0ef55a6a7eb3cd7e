"""A non-editable install works: wheel -> fresh venv -> ``ctsplat --help``, config preparation from the packaged
schema, and a Snakemake dry run of a workflow copy that has no ``ctsplat/`` source folder beside it.

The venv gets the dependencies of the running environment through a ``.pth`` file listing its site-packages
directories. Paths in a ``.pth`` file are appended to ``sys.path`` without processing the ``.pth`` files inside
them, so the running environment's editable-install finder is not installed and ``ctsplat`` can only come from the
wheel. (``--system-site-packages`` alone would expose the base interpreter's packages, not this venv's.)
"""

from __future__ import annotations

import os
import shutil
import site
import subprocess
import sys
from pathlib import Path

import pytest
from smk_helpers import ROOT, job_counts

pytestmark = pytest.mark.workflow


def _run(cmd: list[str], cwd: Path, env: dict[str, str], timeout: int = 600) -> subprocess.CompletedProcess:
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, f"{' '.join(map(str, cmd))} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-5000:]}"
    return proc


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, str], Path]:
    """(venv python, environment without PYTHONPATH, a scratch folder) with ctsplat installed from a wheel."""
    tmp = tmp_path_factory.mktemp("install")
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    # Build from a copy so no build/ or *.egg-info lands in the repository.
    src = tmp / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    shutil.copytree(ROOT / "ctsplat", src / "ctsplat", ignore=shutil.ignore_patterns("__pycache__", "*.pyc", "*.so"))
    _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index", "-q", "-w",
          str(tmp / "wheels"), str(src)], tmp, env)
    wheel = next((tmp / "wheels").glob("ctsplat-*.whl"))

    venv = tmp / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", "--system-site-packages", str(venv)], tmp, env)
    python = venv / "bin" / "python"
    _run([sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps", "--no-index", "-q",
          str(wheel)], tmp, env)
    venv_site = Path(_run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], tmp,
                          env).stdout.strip())
    (venv_site / "_ctsplat_test_dependencies.pth").write_text("\n".join(site.getsitepackages()) + "\n")
    env["PATH"] = f"{venv / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    return python, env, tmp


def test_installed_package_runs_without_the_source_tree(installed):
    python, env, tmp = installed
    venv = python.parent.parent
    probe = (
        "import ctsplat, ctsplat.config as c, yaml\n"
        "from importlib import resources\n"
        "print(ctsplat.__file__)\n"
        "print(resources.files('ctsplat').joinpath('schemas/config.schema.yaml'))\n"
        f"cfg = c.prepare_config(yaml.safe_load(open({str(ROOT / 'config' / 'config.yaml')!r})))\n"
        "print(cfg['grid']['geometry'], cfg['analysis']['milestones'])\n"
    )
    out = _run([str(python), "-c", probe], tmp, env).stdout.splitlines()
    assert Path(out[0]).resolve().is_relative_to(venv.resolve()), out[0]
    assert Path(out[1]).resolve().is_relative_to(venv.resolve()) and Path(out[1]).is_file(), out[1]
    assert out[2] == "circular {'psnr2d': 30.0, 'ssim2d': 0.9, 'psnr3d': 30.0, 'ssim3d': 0.9}"

    help_text = _run([str(venv / "bin" / "ctsplat"), "--help"], tmp, env).stdout
    assert "gather" in help_text and "train" in help_text


def test_workflow_dry_run_with_the_installed_package(installed):
    python, env, tmp = installed
    wf = tmp / "workflow_copy"
    wf.mkdir()
    shutil.copy2(ROOT / "Snakefile", wf / "Snakefile")
    for name in ("workflow", "config", "scripts"):
        shutil.copytree(ROOT / name, wf / name, ignore=shutil.ignore_patterns("__pycache__"))
    assert not (wf / "ctsplat").exists()
    work = tmp / "work"
    work.mkdir()
    proc = _run([str(python), "-m", "snakemake", "-s", str(wf / "Snakefile"), "-d", str(work), "-n", "--cores", "1",
                 "--configfile", str(wf / "config" / "config.yaml")], work, env)
    counts = job_counts(proc.stdout)
    assert counts["gather"] == counts["analyse"] == 1 and counts["train"] >= 2
