"""The safety case's fault table (docs/run/safety.md) is the monitor's own: every bound and blind distance as
`python -m skinsafe.core.runtime.monitor` prints them for the sim's defaults."""
import contextlib
import io
from pathlib import Path

from skinsafe.core.runtime import monitor

PAGE = Path(__file__).resolve().parents[2] / "docs" / "run" / "safety.md"


def test_the_pages_fault_table_is_the_monitors():
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        monitor.main()
    rows = [r for r in out.getvalue().splitlines() if r.startswith("| `")]
    page = [r for r in PAGE.read_text().splitlines() if r.startswith("| `")]
    assert len(rows) == len(monitor.Kind) and rows == page[:len(rows)]
