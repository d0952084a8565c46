"""The command line: help, sensors, and clear errors for bad input."""
import subprocess
import sys

from swathflow.flows.cli import main



def _python(code: str, *argv: str, env=None) -> subprocess.CompletedProcess:
    """``code`` run by a fresh interpreter (``argv``: its arguments), output captured."""
    return subprocess.run([sys.executable, "-c", code, *argv], capture_output=True,
                          text=True, env=env)

def test_help_lists_every_command(capsys):
    try:
        main(["--help"])
    except SystemExit as exc:
        assert exc.code == 0
    out = capsys.readouterr().out
    for cmd in ("sensors", "validate", "simulate", "calibrate", "rectify", "mosaic", "run", "demo"):
        assert cmd in out


def test_sensors_lists_pendulum(capsys):
    assert main(["sensors"]) == 0
    assert "pendulum" in capsys.readouterr().out


def test_console_script_is_installed():
    r = subprocess.run([sys.executable, "-c", "from importlib.metadata import entry_points;"
                        "print([e.value for e in entry_points(group='console_scripts')"
                        " if e.name == 'swathflow'])"], capture_output=True, text=True)
    assert "swathflow.flows.cli:main" in r.stdout


def test_rectify_forks_its_workers_quietly_and_without_distributed(tiny_mission, tmp_path):
    """'swathflow rectify' of several swings: every COG written, no traceback from the
    forked workers at the end (they are closed, not terminated), and no import of
    distributed without a cluster (0.2-0.4 CPU-s of start-up, dask's scheduler lookup)."""
    out = tmp_path / "out"
    code = ("import sys\nfrom swathflow.flows.cli import main\n"
            f"rc = main(['rectify', {str(tiny_mission)!r}, '--out', {str(out)!r}, '-q'])\n"
            "print(rc, sorted(m for m in sys.modules if m.split('.')[0] == 'distributed'))\n")
    r = _python(code)
    assert r.stdout.strip() == "0 []", r.stdout + r.stderr
    assert "Traceback" not in r.stderr, r.stderr
    ids = [line.split("=", 1)[1].strip().strip('"') for line in
           (tiny_mission / "mission.toml").read_text().splitlines()
           if line.replace(" ", "").startswith("id=")]
    assert len(ids) >= 2 and all((out / f"{i}.tif").exists() for i in ids)














def test_rectify_imports_its_engine_without_collector_passes():
    """The rectify command's imports (1,500 modules) run without the collector's passes
    (265 of them, 0.1-0.2 CPU-s on its serial start), and their objects are frozen after;
    the collector is on again after."""
    code = ("import gc, sys\nfrom swathflow.collector import uncollected\n"
            "passes = []\ngc.callbacks.append(lambda phase, info: passes.append(phase))\n"
            "with uncollected():\n"
            "    import xarray\n"
            "print(len(passes), gc.isenabled(), gc.get_freeze_count() > 10000)\n")
    r = _python(code)
    assert r.stdout.split() == ["0", "True", "True"], r.stdout + r.stderr


def _image_ids(mission) -> list[str]:
    return [line.split("=", 1)[1].strip().strip('"') for line in
            (mission / "mission.toml").read_text().splitlines()
            if line.replace(" ", "").startswith("id=")]


def test_rectify_program_ends_with_its_code_every_line_and_every_output(tiny_mission, tmp_path):
    """The swathflow program ends right after 'rectify' returns, without the interpreter's
    teardown (main._leave): its exit code, every progress line through a pipe, every COG
    and rectify.json are there; bad input still ends with one error line and exit 2."""
    import json
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "swathflow.flows.cli", "rectify", str(tiny_mission)]
    r = subprocess.run(cmd + ["--out", str(out)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    ids = _image_ids(tiny_mission)
    lines = r.stdout.splitlines()
    assert len(lines) == len(ids) and all(f"{i}: " in line and f"{i}.tif" in line
                                          for i, line in zip(ids, lines)), r.stdout
    summary = json.loads((out / "rectify.json").read_text())
    assert [s["image_id"] for s in summary["images"]] == ids
    assert all((out / f"{i}.tif").stat().st_size > 0 for i in ids)
    r = subprocess.run(cmd + ["--out", str(tmp_path / "o2"), "--images", "nope"],
                       capture_output=True, text=True)
    errors = [line for line in r.stderr.splitlines() if ": error: " in line]
    assert r.returncode == 2 and len(errors) == 1 and "nope" in errors[0], r.stderr
    assert "Traceback" not in r.stderr


def test_the_program_keeps_openblas_on_one_thread():
    """The program's parallelism is its worker processes and threads: numpy's OpenBLAS
    starts no thread of its own (each spun 0.1 CPU-s at import), unless the environment
    asks."""
    import os

    import pytest
    if not os.path.isdir("/proc/self/task"):
        pytest.skip("needs /proc")
    # the program itself (main() with no argv), asked for its help
    code = ("import os, sys\nfrom swathflow.flows.cli import main\n"
            "sys.argv = ['swathflow', '--help']\n"
            "try:\n    main()\nexcept SystemExit:\n    pass\nimport numpy\n"
            "print(os.environ['OPENBLAS_NUM_THREADS'], len(os.listdir('/proc/self/task')))\n")
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    r = _python(code, env=env)
    assert r.stdout.splitlines()[-1].split() == ["1", "1"], r.stdout + r.stderr
    r = _python(code, env=dict(env, OPENBLAS_NUM_THREADS="2"))
    assert r.stdout.splitlines()[-1].split()[0] == "2", r.stdout + r.stderr


def test_demo_summary_names_the_products_to_open_first(tmp_path):
    """The demo's closing lines give the mosaic's HTML report and quicklook and the
    calibration report with their paths, and leave out what was not written."""
    from swathflow.flows.cli.commands import demo_products, demo_summary
    products = tmp_path / "products"
    (products / "calibration").mkdir(parents=True)
    for name in ("mosaic.tif", "mosaic.html", "mosaic.png", "calibration/report.html"):
        (products / name).write_text("x")
    result = {"mosaic": str(products / "mosaic.tif"),
              "report": str(products / "calibration" / "report.html")}
    assert demo_products(result) == [
        ("mosaic report", str(products / "mosaic.html")),
        ("mosaic quicklook", str(products / "mosaic.png")),
        ("calibration report", str(products / "calibration" / "report.html"))]
    text = demo_summary(result, 61.4)
    assert text.startswith("demo finished in 61 s")
    assert all(str(p) in text for p in (products / "mosaic.html", products / "mosaic.png"))
    (products / "mosaic.png").unlink()
    assert [w for w, _ in demo_products(result)] == ["mosaic report", "calibration report"]
    assert demo_products({"mosaic": None, "report": None}) == []


def test_demo_folder_inside_a_clone_leaves_git_status_clean(tmp_path):
    """The demo's folder marks itself ignored by git (what it writes, its lock included);
    a folder holding a person's own files is left alone."""
    from swathflow.flows.cli.commands import ignored_by_git
    subprocess.run(["git", "init", "-q", str(tmp_path)], check=True)
    demo = tmp_path / "swathflow-demo"
    demo.mkdir()
    (demo / ".swathflow.lock").write_text("1\n")
    ignored_by_git(demo)
    for name in ("mission/mission.toml", "products/mosaic.tif"):
        (demo / name).parent.mkdir(exist_ok=True)
        (demo / name).write_text("x")
    status = subprocess.run(["git", "status", "--porcelain", "--untracked-files=all"],
                            cwd=tmp_path, capture_output=True, text=True, check=True)
    assert status.stdout == ""
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("x")
    ignored_by_git(mine)
    assert not (mine / ".gitignore").exists()
