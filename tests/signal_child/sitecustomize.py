"""Imported at start-up by a child ``python -m afmid.cli`` whose PYTHONPATH holds this folder (the fault corpus,
tests/cli/test_corpus_faults.py): sends the process a real signal at a chosen moment of its run.

Environment (read once, then removed, so that processes it starts, e.g. batch workers, do not act too):

- ``AFMID_TEST_SIGNAL``: SIGINT or SIGTERM (the signal, sent to this process only, as ``kill`` would);
- ``AFMID_TEST_SIGNAL_WHEN``: a glob relative to the working folder; the signal goes once something matches
  (e.g. ``.afmid-tmp-*``: the write phase has begun); or ``audit:EVENT:TEXT``: once the main thread raises
  the audit event EVENT with TEXT in its arguments (e.g. ``audit:open:trace.h5``: the input is read);
  or, if empty, right away;
- ``AFMID_TEST_SIGNAL_NONEMPTY=1``: with a glob, only a file that already holds bytes counts (the output's
  temporary file once written to, not the empty probe that checks the folder is writable before the fit);
- ``AFMID_TEST_SIGNAL_DELAY``: seconds to wait after that (default 0);
- or ``AFMID_TEST_SIGNAL_AT``: an audit event (e.g. ``tempfile.mkstemp``, raised as a temporary file is
  made): the main thread sends the signal itself the first time it raises that event, so it arrives at
  exactly that point; with ``AFMID_TEST_SIGNAL_IN_CALLBACK=1`` it sends it from inside a weakref callback,
  where Python cannot propagate the exception its handler raises: what happens when a real Ctrl-C lands
  while h5py or NumPy objects are being released (measured: most Ctrl-Cs in ``afmid fit``'s write phase).

SIGINT is first reset to Python's default: a test suite started in the background by a non-interactive shell
inherits SIGINT ignored, and the child would then never see the Ctrl-C it stands for.
"""

import os

_signal_name = os.environ.pop("AFMID_TEST_SIGNAL", "")
if _signal_name:
    import glob
    import signal
    import threading
    import time

    _when = os.environ.pop("AFMID_TEST_SIGNAL_WHEN", "")
    _delay = float(os.environ.pop("AFMID_TEST_SIGNAL_DELAY", "0") or 0)
    _nonempty = os.environ.pop("AFMID_TEST_SIGNAL_NONEMPTY", "") == "1"
    _at = os.environ.pop("AFMID_TEST_SIGNAL_AT", "")
    _in_callback = os.environ.pop("AFMID_TEST_SIGNAL_IN_CALLBACK", "") == "1"
    signal.signal(signal.SIGINT, signal.default_int_handler)

    _seen = threading.Event()

    def _send() -> None:
        deadline = time.monotonic() + 100
        if _when.startswith("audit:"):
            _seen.wait(100)
        def _matched() -> bool:
            for path in glob.glob(_when):
                try:
                    if not _nonempty or os.path.getsize(path) > 0:
                        return True
                except OSError:  # removed between the glob and the size
                    pass
            return False

        while _when and not _when.startswith("audit:") and not _matched() and time.monotonic() < deadline:
            time.sleep(0.001)
        time.sleep(_delay)
        os.kill(os.getpid(), getattr(signal, _signal_name))

    if _at:
        import sys
        import weakref

        class _Released:
            pass

        _sent = []

        def _audit(event, args) -> None:
            if event != _at or _sent or threading.current_thread() is not threading.main_thread():
                return
            _sent.append(event)
            if not _in_callback:
                os.kill(os.getpid(), getattr(signal, _signal_name))
                return
            obj = _Released()
            # os.kill delivers a signal to the own process at once: the handler runs inside the callback.
            ref = weakref.ref(obj, lambda _: os.kill(os.getpid(), getattr(signal, _signal_name)))
            del obj
            del ref

        sys.addaudithook(_audit)
    else:
        if _when.startswith("audit:"):
            import sys

            _, _event, _text = _when.split(":", 2)

            def _watch(event, args) -> None:
                if event == _event and _text in repr(args) and threading.current_thread() is threading.main_thread():
                    _seen.set()

            sys.addaudithook(_watch)
        threading.Thread(target=_send, name="test-signal", daemon=True).start()
