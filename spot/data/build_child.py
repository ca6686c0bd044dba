"""Recipe builds in a child process without ``SPOT_FAST_COMPILE``'s XLA flags.

XLA's fast-compile flags (:data:`spot.runtime.FAST_COMPILE_FLAGS`) change what a recipe's jax code
computes: a small Hopper build under ``SPOT_FAST_COMPILE=1`` is another SAC run (docs/datasets.md).
A dataset file is keyed by name, size, seed and recipe version only, so a process with fast compile
on (the switch, or the flags in ``XLA_FLAGS``: :func:`needed`) runs a recipe build in a child process
with the flags removed (:func:`run`): XLA reads its flags once, when a backend starts, so the
process cannot drop them itself. Any recipe build goes to the child, whether or not its recipe runs
jax (which a recipe does not declare); copying the embedded build runs no recipe and stays here.

The child, ``python -m spot.data.build_child NAME SIZE SEED``, runs the recipe and writes the file
and its card (:func:`spot.data.registry.build_unlocked`, whose card records the child's
``XLA_FLAGS``); it takes no lock: the parent holds the dataset's locks while it waits for it.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import subprocess
import sys
from collections.abc import Mapping

from spot import SpotError, runtime


def needed() -> bool:
    """Whether this process runs a recipe build in a child: ``SPOT_FAST_COMPILE`` is on or
    ``XLA_FLAGS`` holds one of :data:`spot.runtime.FAST_COMPILE_FLAGS`."""
    flags = os.environ.get("XLA_FLAGS", "").split()
    return runtime.fast_compile() or any(f in flags for f in runtime.FAST_COMPILE_FLAGS)


def child_env(environ: Mapping[str, str] = os.environ) -> dict[str, str]:
    """``environ`` with ``SPOT_FAST_COMPILE=0`` and ``XLA_FLAGS`` without the fast-compile flags."""
    env = dict(environ)
    env[runtime.FAST_COMPILE_SWITCH] = "0"
    env["XLA_FLAGS"] = " ".join(f for f in env.get("XLA_FLAGS", "").split() if f not in runtime.FAST_COMPILE_FLAGS)
    return env


def run(name: str, size: str, seed: int, progress: bool = True) -> None:
    """Build ``name`` at ``size``/``seed`` with its recipe in a child process with the normal XLA
    flags; the caller holds the dataset's locks. The child's output goes to stderr when
    ``progress``. Raises :class:`SpotError` with the child's last output line if it fails."""
    cmd = [sys.executable, "-m", "spot.data.build_child", name, size, str(seed), *([] if progress else ["--quiet"])]
    if progress:
        print(f"spot: building {name} ({size}, seed {seed}) in a process without SPOT_FAST_COMPILE", file=sys.stderr)
    proc = subprocess.Popen(
        cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=child_env()
    )
    last = ""
    try:
        for line in proc.stderr or ():
            if progress:
                sys.stderr.write(line)
            last = line.strip() or last
        rc = proc.wait()
    finally:
        if proc.poll() is None:  # interrupted: the child's temp file is removed as stale later
            proc.kill()
            proc.wait()
    if rc != 0:
        raise SpotError(
            f"dataset {name} ({size}, seed {seed}): its build in a process without SPOT_FAST_COMPILE failed "
            f"(exit {rc}): {last.removeprefix('error: ') or 'no output'}"
        )


def main(argv: list[str] | None = None) -> int:
    """The child: build one dataset with its recipe (no lock: the parent holds it); 2 on a
    :class:`SpotError`, printed as one ``error:`` line."""
    parser = argparse.ArgumentParser(prog="python -m spot.data.build_child", description=__doc__)
    parser.add_argument("name")
    parser.add_argument("size")
    parser.add_argument("seed", type=int)
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)
    try:
        runtime.configure()
        if needed():
            raise SpotError(f"XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r} holds a fast-compile flag")
        from spot.data import registry

        with contextlib.redirect_stdout(sys.stderr):
            registry.build_unlocked(args.name, args.size, args.seed, progress=not args.quiet)
    except SpotError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
