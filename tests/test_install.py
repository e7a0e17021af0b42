"""The installed package: its package list, the benchmark scripts shipped as
``torchcbf.scripts`` and found by ``torchcbf bench`` outside any checkout, and the CLI's
help, version and exit codes."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

import torchcbf
from torchcbf.cli import BENCHES, DESCRIPTIONS, main

ROOT = Path(__file__).resolve().parents[1]


def test_package_list_covers_the_source_tree() -> None:
    tomllib = pytest.importorskip("tomllib")
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    found = {
        ".".join(p.parent.relative_to(ROOT).parts) for p in (ROOT / "torchcbf").rglob("__init__.py")
    }
    assert set(config["packages"]) == found | {"torchcbf.scripts"}
    assert config["package-dir"] == {"torchcbf.scripts": "scripts"}


@pytest.mark.slow
def test_wheel_ships_the_benchmarks_and_bench_finds_them_outside_a_checkout(tmp_path) -> None:
    src = tmp_path / "src"
    ignore = shutil.ignore_patterns("__pycache__", "*.so", "*.egg-info", "build")
    for name in ("torchcbf", "scripts"):
        shutil.copytree(ROOT / name, src / name, ignore=ignore)
    for name in ("pyproject.toml", "setup.py", "README.md"):
        shutil.copy(ROOT / name, src / name)
    built = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation",
         "-w", str(tmp_path / "dist"), str(src)],
        capture_output=True, text=True,
    )  # fmt: skip
    assert built.returncode == 0, built.stderr[-2000:]
    (wheel,) = (tmp_path / "dist").glob("torchcbf-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    for bench in BENCHES:
        assert f"torchcbf/scripts/{bench}" in names
    assert "torchcbf/envs/__init__.py" in names and "torchcbf/sweep/tune.py" in names
    site = tmp_path / "site"
    installed = subprocess.run(
        [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", str(site),
         str(wheel)],
        capture_output=True, text=True,
    )  # fmt: skip
    assert installed.returncode == 0, installed.stderr[-2000:]
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = {**os.environ, "PYTHONPATH": str(site)}
    listed = subprocess.run(
        [sys.executable, "-c",
         "import sys, torchcbf; from torchcbf.cli import main; print(torchcbf.__file__); "
         "sys.exit(main(['bench', '--list']))"],
        capture_output=True, text=True, cwd=elsewhere, env=env,
    )  # fmt: skip
    assert listed.returncode == 0, listed.stderr[-2000:]
    lines = listed.stdout.splitlines()
    assert lines[0].startswith(str(site))  # the installed copy, not the checkout
    paths = [line.split()[-1] for line in lines[1:]]
    assert [Path(p).name for p in paths] == list(BENCHES)
    assert all(p.startswith(str(site / "torchcbf" / "scripts")) for p in paths)


def test_bench_lists_and_filters(capsys) -> None:
    assert main(["bench", "--list"]) == 0
    out = capsys.readouterr().out
    assert [line.split()[0] for line in out.splitlines()] == ["qp", "barriers", "filters", "mppi"]
    assert main(["bench", "--list", "--only", "mppi,qp"]) == 0
    assert [line.split()[0] for line in capsys.readouterr().out.splitlines()] == ["qp", "mppi"]


def test_bench_exits_non_zero_when_nothing_runs(capsys, monkeypatch) -> None:
    assert main(["bench", "--only", "nothing"]) == 2
    assert "no benchmark" in capsys.readouterr().err
    monkeypatch.setattr("torchcbf.cli._bench_scripts", lambda: [])
    assert main(["bench", "--quick"]) == 2
    assert "no benchmark scripts found" in capsys.readouterr().err


def test_bench_reports_a_failing_script(tmp_path, capsys, monkeypatch) -> None:
    script = tmp_path / "bench_broken.py"
    script.write_text("import sys\nsys.exit(3)\n")
    monkeypatch.setattr("torchcbf.cli._bench_scripts", lambda: [script])
    assert main(["bench"]) == 1
    assert "failed: bench_broken.py" in capsys.readouterr().err


def test_version(capsys) -> None:
    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0
    assert capsys.readouterr().out.strip().startswith(f"torchcbf {torchcbf.__version__}")


@pytest.mark.parametrize("command", sorted(DESCRIPTIONS))
def test_every_subcommand_has_a_description_and_shows_defaults(command, capsys) -> None:
    with pytest.raises(SystemExit) as stop:
        main([command, "--help"])
    assert stop.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    assert " ".join(DESCRIPTIONS[command].split())[:60] in text
    if command != "info":  # the only command without a device
        assert "(default: cpu)" in text


def _source_copy(dest: Path, *, with_setup: bool) -> Path:
    """The package's sources under ``dest`` (no built kernels); without ``setup.py`` no C
    extension is built, which keeps a build to a few seconds."""
    ignore = shutil.ignore_patterns("__pycache__", "*.so", "*.egg-info", "build")
    for name in ("torchcbf", "scripts"):
        shutil.copytree(ROOT / name, dest / name, ignore=ignore)
    for name in ("pyproject.toml", "README.md", "LICENSE") + (("setup.py",) if with_setup else ()):
        shutil.copy(ROOT / name, dest / name)
    return dest


def test_editable_install_is_a_path_that_type_checkers_and_the_parent_folder_see(tmp_path):
    """`pip install -e .` builds a compat editable wheel: its .pth holds the checkout's
    folder (type checkers follow such paths, not import hooks), and Python started in the
    clone's parent folder imports the package rather than the clone as a namespace."""
    clone = _source_copy(tmp_path / "torchcbf", with_setup=False)  # a clone's default name
    built = subprocess.run(
        [sys.executable, "-c",
         "from setuptools import build_meta as b; print(b.build_editable('dist'))"],
        capture_output=True, text=True, cwd=clone,
    )  # fmt: skip
    assert built.returncode == 0, built.stderr[-2000:]
    wheel = clone / "dist" / built.stdout.strip().splitlines()[-1]
    names = zipfile.ZipFile(wheel).namelist()
    (pth,) = [n for n in names if n.endswith(".pth")]
    assert not [n for n in names if n.endswith("_finder.py")]  # no import hook
    assert zipfile.ZipFile(wheel).read(pth).decode().strip() == str(clone)
    # Python as the compat install leaves it: site-packages, then the .pth's path; -S keeps
    # this interpreter's own torchcbf install (an import hook or another .pth) out of it
    import site

    path = [*site.getsitepackages(), str(clone)]
    found = subprocess.run(
        [sys.executable, "-S", "-c",
         f"import sys; sys.path.extend({path!r}); import torchcbf; print(torchcbf.__file__)"],
        capture_output=True, text=True, cwd=tmp_path,
    )  # fmt: skip
    assert found.returncode == 0, found.stderr[-2000:]
    installed = any((Path(p) / "torchcbf" / "__init__.py").exists() for p in path[:-1])
    expected = "site-packages" if installed else str(clone / "torchcbf" / "__init__.py")
    assert found.stdout.strip().endswith("torchcbf/__init__.py")  # a package, not the clone
    assert expected in found.stdout


def test_sdist_holds_what_a_build_needs(tmp_path) -> None:
    src = _source_copy(tmp_path / "src", with_setup=True)
    built = subprocess.run(
        [sys.executable, "-c",
         "from setuptools import build_meta as b; print(b.build_sdist('dist'))"],
        capture_output=True, text=True, cwd=src,
    )  # fmt: skip
    assert built.returncode == 0, built.stderr[-2000:]
    import tarfile

    sdist = src / "dist" / built.stdout.strip().splitlines()[-1]
    names = {n.split("/", 1)[1] for n in tarfile.open(sdist).getnames() if "/" in n}
    sources = [p.relative_to(ROOT).as_posix() for p in (ROOT / "torchcbf").rglob("*.[ch]")]
    for name in ("LICENSE", "README.md", "setup.py", "pyproject.toml", "torchcbf/py.typed",
                 "torchcbf/assets/arm7.urdf", "scripts/bench_qp.py", *sources):  # fmt: skip
        assert name in names, name


def test_metadata_names_the_license_file_and_the_changelog_has_the_version() -> None:
    tomllib = pytest.importorskip("tomllib")
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["license"] == "MIT" and project["license-files"] == ["LICENSE"]
    assert (ROOT / "LICENSE").read_text().startswith("MIT License")
    changelog = (ROOT / "CHANGELOG.md").read_text()
    assert f"## {torchcbf.__version__}" in changelog and "## Unreleased" in changelog


def test_ci_reads_the_readme_commands() -> None:
    """.ci/run takes the test command from the README's first code block (the line that runs
    pytest) and splits it at '&& .venv/bin/python -m pytest'; the block also starts with the
    install-and-demo command."""
    ci = subprocess.run(
        ["awk", "/^```/{n++; next} n==1 && /pytest/", str(ROOT / "README.md")],
        capture_output=True, text=True, check=True,
    )  # fmt: skip
    test_cmd = ci.stdout.splitlines()[0]
    assert "&& .venv/bin/python -m pytest" in test_cmd
    assert test_cmd.startswith("python3 -m venv .venv && .venv/bin/pip install torch==")
    first_block = (ROOT / "README.md").read_text().split("```")[1]
    commands = [line for line in first_block.splitlines() if line.startswith("python3 -m venv")]
    assert len(commands) == 2 and "torchcbf demo" in commands[0] and commands[1] == test_cmd
