"""``fbg-accel-calib`` leaves the interpreter's last garbage collections nothing to walk: ``cli_main.main`` registers
an exit handler, once however often it runs in one process, that freezes the objects then alive (its libraries'
modules, a diagnosis' results) out of them."""

from __future__ import annotations

import atexit
import gc

import pytest

from fbg_accel_calibration.commands import cli_main


def test_the_command_freezes_what_is_left_at_exit_once(monkeypatch: pytest.MonkeyPatch,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    handlers: list = []

    def unregister(func) -> None:
        handlers[:] = [h for h in handlers if h is not func]

    monkeypatch.setattr(atexit, "register", handlers.append)
    monkeypatch.setattr(atexit, "unregister", unregister)
    for _ in range(2):
        with pytest.raises(SystemExit):
            cli_main.main(["--help"])
    assert "usage" in capsys.readouterr().out
    assert handlers == [cli_main._freeze_at_exit]  # one for the two runs
    before = gc.get_freeze_count()
    try:
        handlers[0]()
        assert gc.get_freeze_count() > before + 1000  # the modules' objects, not a handful
    finally:
        gc.unfreeze()
