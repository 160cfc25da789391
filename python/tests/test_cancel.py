"""Progress callbacks and cancellation of every long call: validation, surface extraction,
export (surface and volume), fits, Hermite fits and smoothing.

A callback that raises at its first report makes the call raise that exception, and the call's
worker thread has ended when it does (the libraries stop at their next unit of work; the Rust
tests in crates/*/tests/cancel.rs check that no further work is done). No timing is asserted."""
import json
import os
import pathlib

import pytest

import ism

ROOT = pathlib.Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "spec" / "examples"
HERMITE = EXAMPLES / "hermite" / "ellipse.hermite.json"


# How long a joined worker may still be listed. The call returns after joining its worker, but
# Linux wakes the joiner when the exiting thread releases its memory map (the thread id is
# cleared in `mm_release`), before the task is unlisted from /proc (`release_task`): on a loaded
# machine the entry can outlive the join by a few scheduler ticks (CI saw it once in 438 runs).
# This check therefore catches a worker left running, not one ending a moment late; that no work
# is done after a cancel is checked by the Rust tests in crates/*/tests/cancel.rs.
UNLISTED_WITHIN_S = 5.0


def worker_threads():
    """Threads of this process named like the package's worker (Linux: /proc/self/task), once
    the ones that have ended are unlisted (waits up to `UNLISTED_WITHIN_S` for the count to
    reach 0)."""
    import time

    tasks = pathlib.Path("/proc/self/task")
    if not tasks.is_dir():
        pytest.skip("needs /proc/self/task to list threads")
    deadline = time.monotonic() + UNLISTED_WITHIN_S
    while True:
        names = []
        for t in tasks.iterdir():
            try:
                names.append((t / "comm").read_text().strip())
            except OSError:
                pass  # the thread ended while listing
        count = names.count("ism-worker")
        if count == 0 or time.monotonic() > deadline:
            return count
        time.sleep(0.01)


def sphere():
    return ism.read(EXAMPLES / "sphere.ismb")


# (name, call with a progress callback): each a long call of the package.
CALLS = [
    ("validate", lambda cb: ism.read(EXAMPLES / "stratified-3d.ismb").validate(theorems=False, progress=cb)),
    ("validate path", lambda cb: ism.validate(EXAMPLES / "stratified-3d.ismb", theorems=False, progress=cb)),
    ("validate bytes", lambda cb: ism.validate((EXAMPLES / "stratified-3d.ismb").read_bytes(), theorems=False, progress=cb)),
    ("extract_surface", lambda cb: sphere().extract_surface(1e-4, progress=cb)),
    ("export", lambda cb: sphere().export(cb.tmp / "s.glb", tolerance=1e-4, progress=cb)),
    ("export volume", lambda cb: ism.read(EXAMPLES / "torus.ismb").export(cb.tmp / "v.vtu", volume=True, progress=cb)),
    ("smooth", lambda cb: ism.fit("x^2 + y^2 - 0.25", (-1, 1, -1, 1), resolution=5)[0].smooth(iterations=3, progress=cb)),
    ("fit_hermite", lambda cb: ism.fit_hermite(json.loads(HERMITE.read_text()), progress=cb)),
    ("fit", lambda cb: ism.fit("x^2 + y^2 - 0.25", (-1, 1, -1, 1), resolution=5, progress=cb)),
]


class Recorder:
    """A progress callback recording its arguments; with `stop`, it raises `stop` at its first
    report."""

    def __init__(self, tmp, stop=None):
        self.tmp, self.stop, self.seen = tmp, stop, []

    def __call__(self, *args):
        self.seen.append(args)
        if self.stop is not None:
            raise self.stop


@pytest.mark.parametrize("name,call", CALLS, ids=[c[0] for c in CALLS])
def test_progress_is_reported(name, call, tmp_path):
    cb = Recorder(tmp_path)
    call(cb)
    assert cb.seen, f"{name}: no progress reported"
    for phase, done, third in cb.seen:
        assert isinstance(phase, str) and phase
        assert isinstance(done, int) and done >= 0
    if name != "fit":  # fit's third argument is the worst error so far
        counted = [s for s in cb.seen if s[2] > 0]
        assert counted, f"{name}: no counted phase"
        assert all(done <= total for _, done, total in counted)
        # A counted phase ends at its total.
        assert any(done == total for _, done, total in counted)
    assert worker_threads() == 0


@pytest.mark.parametrize("name,call", CALLS, ids=[c[0] for c in CALLS])
def test_a_callback_that_raises_stops_the_call(name, call, tmp_path):
    cb = Recorder(tmp_path, KeyboardInterrupt)
    with pytest.raises(KeyboardInterrupt):
        call(cb)
    # The callback is not called again once it raised, and the worker has ended: nothing runs on.
    assert len(cb.seen) == 1
    assert worker_threads() == 0
    # Nothing half-written.
    assert not any(tmp_path.iterdir())


def test_the_model_is_usable_after_a_cancelled_call():
    m = sphere()
    with pytest.raises(KeyboardInterrupt):
        m.extract_surface(1e-4, progress=Recorder(None, KeyboardInterrupt))
    assert m.extract_surface(1e-2).report["euler_characteristic"] == 2
    assert m.validate().verdict == "valid"


def test_ctrl_c_stops_a_validation_and_its_worker():
    import subprocess
    import sys

    # SIGINT sent by another thread at the first progress report (as a terminal's Ctrl-C arrives,
    # while the call waits): the call raises KeyboardInterrupt and, when it has, no worker
    # thread is left.
    child = f"""
import os, signal, sys, threading
# A process started in the background by a non-interactive shell inherits SIGINT ignored, and
# Python then installs no KeyboardInterrupt handler: install it, as an interactive session has it.
signal.signal(signal.SIGINT, signal.default_int_handler)
sys.path.insert(0, {str(pathlib.Path(__file__).parent)!r})
import ism
from test_cancel import worker_threads
m = ism.read({str(EXAMPLES / "stratified-3d.ismb")!r})
reports = []
def first(*args):
    reports.append(args)
    if len(reports) == 1:
        threading.Thread(target=os.kill, args=(os.getpid(), signal.SIGINT)).start()
try:
    m.validate(theorems=False, progress=first)
    print("finished")
except KeyboardInterrupt:
    print("interrupted", worker_threads())
print(m.validate().verdict)
"""
    done = subprocess.run([sys.executable, "-c", child], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["interrupted", "0", "valid"], done.stdout
