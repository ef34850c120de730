"""The one-line refusal a CLI command prints: shared by the tests that check a command's error message."""

from __future__ import annotations


def one_line_error(capsys, code, *words) -> str:
    """The one ``uvatar: error:`` line of a command that refused: exit 1, no traceback (nor an ignored
    exception), exactly one error line, containing every one of ``words``."""
    text = capsys.readouterr().err
    assert "Traceback" not in text and "Exception ignored" not in text, text[-3000:]
    err = [line for line in text.splitlines() if line.startswith("uvatar: error: ")]
    assert code == 1, (code, text[-2000:])
    assert len(err) == 1, text[-2000:]
    for word in words:
        assert word in err[0], (word, err[0])
    return err[0]
