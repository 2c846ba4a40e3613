"""The demo report page: pictures embedded at their own size, wide tables scrolling inside the
page, numbers people can read."""
import base64
import re

from skinsafe.core.app.report import Section, write_report

PNG = base64.b64decode("iVBORw0KGgoAAAANSUhEUgAAAAEAAAABCAYAAAAfFcSJAAAADUlEQVR42mP8z8DwHwAFBQIAX8jx0gAAAABJRU5ErkJggg==")


def test_report_embeds_pictures_and_keeps_tables_readable(tmp_path):
    pic = tmp_path / "p.png"
    pic.write_bytes(PNG)
    rows = [{"n_taxels": 4134, "steps_per_s": 32885.4, "overhead": 0.2531, "kernel": "19 pt/taxel"}]
    path = write_report(tmp_path / "r.html", "T", "intro", [
        Section("S", "one\n\ntwo", images=[(str(pic), "a <robot>"), (str(tmp_path / "gone.png"), "x")],
                tables=[(rows, "what it means")])])
    page = path.read_text()
    assert page.count("data:image/png;base64,") == 1 and "missing picture" in page
    assert "a &lt;robot&gt;" in page  # captions escaped
    assert "<td>32,885</td>" in page and "<td>0.2531</td>" in page and "<td>4134</td>" in page
    assert re.search(r"<div class='scroll'><table>", page) and "overflow-x:auto" in page
    assert "max-width:520px" not in page  # pictures are not shrunk to half the page
