"""The ``spot`` command as a package (spot/cli/): building its parser stays light, the choices it
writes out are the library's, and both entry points (``spot.cli:main``, ``python -m spot.cli``) work."""

import json
import subprocess
import sys

HEAVY = ("jax", "mlflow", "ray", "pandas", "scipy")


def test_help_imports_no_heavy_library():
    """`spot --help` and building every subcommand's parser import none of JAX, MLflow, Ray, pandas
    or SciPy (the handlers import them when they run). A fresh interpreter: this process has them."""
    code = (
        "import contextlib, io, json, sys\n"
        "from spot import cli\n"
        "cli.build_parser()\n"
        "with contextlib.redirect_stdout(io.StringIO()) as out:\n"
        "    try:\n"
        "        cli.main(['--help'])\n"
        "    except SystemExit as e:\n"
        "        code = e.code\n"
        f"loaded = sorted({{m.split('.')[0] for m in sys.modules}} & set({HEAVY!r}))\n"
        "print(json.dumps([code, 'usage: spot' in out.getvalue(), loaded]))\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    code, shown, loaded = json.loads(done.stdout.strip().splitlines()[-1])
    assert code == 0 and shown
    assert loaded == [], f"building the parser imported {loaded}; import them inside the handlers"


def test_the_checker_sees_a_heavy_import():
    """The same check in a process that imports pandas: it must report it."""
    code = f"import sys, pandas\nprint(sorted({{m.split('.')[0] for m in sys.modules}} & set({HEAVY!r})))"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert "pandas" in done.stdout


def test_the_choices_written_out_are_the_librarys():
    from spot.cli import common
    from spot.data import registry
    from spot.results import table_format, tables

    assert common.SIZES == registry.SIZES
    assert common.TABLES == tuple(tables.TABLES)
    assert common.FORMATS == tuple(table_format.FORMATS)


def test_console_script_and_module_entry_points():
    from importlib.metadata import entry_points

    from spot import cli

    (script,) = [e for e in entry_points(group="console_scripts") if e.name == "spot"]
    assert script.value == "spot.cli:main" and script.load() is cli.main
    done = subprocess.run([sys.executable, "-m", "spot.cli", "--version"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout.startswith("spot ")
    bad = subprocess.run([sys.executable, "-m", "spot.cli", "tables"], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "the following arguments are required: --table" in bad.stderr
