"""What a reader sees in the report, overlays and summaries (issue 12, items 4 and 5).

Rejection reasons are counted by kind (no numbers) whatever their wording; the page
uses written labels, names the sweep's file, explains holes, puts the simulated result
beside the paper's with its caveat; 3D views carry a scale bar and an orientation
triad, and their colour-bar title does not touch the tick labels; overlay banners wrap
and scale with the frame; the Table I plot starts at 0 mm.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from BoneUSRecon.cli import main
from BoneUSRecon.Logic.reasons import count_reasons, format_reason_counts, reason_key
from BoneUSRecon.Widgets import render
from BoneUSRecon.Widgets.overlay import label_font_size, label_lines, overlay_image
from BoneUSRecon.Widgets.report import human_label, table_figure


# -- reasons --------------------------------------------------------------------------
def test_jump_values_make_one_reason_kind() -> None:
    rejected = {
        25: "jump of 3.0 mm from neighbouring frames",
        27: "jump of 4.5 mm from neighbouring frames",
        47: "no bone found",
        55: "contour too short after dropping off-neighbour points (0.0 mm)",
    }
    counts = count_reasons(rejected)
    assert counts == {
        "jump from neighbouring frames": 2,
        "contour too short after dropping off-neighbour points": 1,
        "no bone found": 1,
    }
    assert format_reason_counts(counts).startswith("jump from neighbouring frames: 2; ")


@settings(max_examples=200, deadline=None)
@given(st.text(max_size=80))
@example(":<:<")  # a key starting with a separator was not its own key
@example("\r:<:<")  # nor one after a carriage return (whitespace other than a space)
def test_any_reason_string_gives_a_short_key_without_numbers(text: str) -> None:
    key = reason_key(text)
    assert key and not re.search(r"\d", key) and "\n" not in key
    assert reason_key(key) == key  # normalising twice changes nothing


def test_segment_summary_counts_reasons_by_kind(
    sim_small_corrupted, tmp_path: Path, capsys
) -> None:
    from BoneUSRecon.Logic.sequence_io import write_sweep

    sweep = write_sweep(sim_small_corrupted.sweep, tmp_path / "s.mha")
    assert main(["segment", str(sweep), "-o", str(tmp_path / "p.vtp"), "-q", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["rejected"] >= 1
    assert sum(doc["rejection_reasons"].values()) == doc["rejected"]
    assert not any(re.search(r"\d|#", k) for k in doc["rejection_reasons"])
    # The per-frame reasons keep their numbers.
    assert set(doc["rejected_frames"]) and all(doc["rejected_frames"].values())
    assert main(["segment", str(sweep), "-o", str(tmp_path / "p.vtp"), "-q"]) == 0
    out = capsys.readouterr().out
    widths = {len(line.split(" : ")[0]) for line in out.splitlines()[1:] if " : " in line}
    assert max(widths) <= 2 + 26 + 2 or len(widths) > 1  # long keys do not pad every row


# -- the page -------------------------------------------------------------------------
@pytest.fixture(scope="module")
def demo_page(tmp_path_factory: pytest.TempPathFactory) -> SimpleNamespace:
    out = tmp_path_factory.mktemp("demo_page") / "d"
    argv = [
        "demo",
        str(out),
        "--frames",
        "40",
        "--size",
        "160x128",
        "--corrupted",
        "0.1",
        "--seed",
        "1",
        "--no-table",
        "-q",
        "--json",
    ]
    assert main(argv) == 0
    page = (out / "report" / "index.html").read_text(encoding="utf-8")
    return SimpleNamespace(
        out=out, page=page, numbers=json.loads((out / "report" / "report.json").read_text())
    )


def _th_labels(page: str, table_id: str) -> list[str]:
    table = re.search(rf'<table id="{table_id}">(.*?)</table>', page, flags=re.S).group(1)
    return re.findall(r"<th>(.*?)</th>", table)


def test_page_labels_are_words_not_keys(demo_page: SimpleNamespace) -> None:
    labels = _th_labels(demo_page.page, "reconstruction")
    assert len(labels) >= 15
    assert not [t for t in labels if "_" in t], labels
    assert "frames discarded by the robust fit" in labels and "surface area" in labels
    for key in demo_page.numbers["reconstruction"]:  # every summary key has a label
        assert "_" not in human_label(key)
    assert human_label("new_thing_mm") == "new thing"


def test_page_names_the_written_sweep_and_counts_reasons_without_numbers(
    demo_page: SimpleNamespace,
) -> None:
    table = re.search(r'<table id="sweep">(.*?)</table>', demo_page.page, flags=re.S).group(1)
    rows = dict(re.findall(r"<tr><th>(.*?)</th><td>(.*?)</td></tr>", table, flags=re.S))
    assert rows["source"] == str(demo_page.out / "sweep.mha")
    assert "(in memory)" not in demo_page.page
    rejected = rows["frames rejected by the segmentation"]
    reasons = re.sub(r"<[^>]+>", "", rejected).split("(", 1)[1]
    assert "#" not in reasons
    assert re.fullmatch(r"[^\d]+: \d+(; [^\d]+: \d+)*\)", reasons), reasons


def test_headline_has_the_simulation_caveat_and_holes_are_explained(
    demo_page: SimpleNamespace,
) -> None:
    caveat = re.search(r'<p id="headline-caveat"[^>]*>(.*?)</p>', demo_page.page).group(1)
    assert "simulated" in caveat and "not like for like" in caveat
    holes = re.search(r'<p id="holes-note">(.*?)</p>', demo_page.page, flags=re.S).group(1)
    assert "trimmed to the data" in holes and "% of the" in holes
    assert "scale bar" in demo_page.page and "triad" in demo_page.page


# -- 3D pictures ----------------------------------------------------------------------
@pytest.fixture(scope="module")
def cylinder_view(sim_small) -> np.ndarray:
    import pyvista as pv

    mesh = pv.Cylinder(radius=5.0, height=60.0, direction=(1, 0, 0), resolution=40).triangulate()
    mesh.point_data["Distance"] = np.abs(np.asarray(mesh.points)[:, 0]) / 30.0
    # With the sweep's frame outlines: other geometry once changed the bar's layout.
    return render.render_views(
        mesh, sweep=sim_small.sweep, show_frames=True, views=("top",), window_size=(800, 480)
    )["top"]


def test_colour_bar_title_above_the_strip_and_labels_below(cylinder_view: np.ndarray) -> None:
    img = cylinder_view.astype(int)
    h, w, _ = img.shape
    x0, x1 = int(0.32 * w), int(0.68 * w)  # inside the bar (x 0.3 to 0.7)
    band = img[int(0.7 * h) :, x0:x1]
    sat = band.max(axis=2) - band.min(axis=2)
    strip = np.flatnonzero((sat > 60).mean(axis=1) > 0.9)  # rows of the colour strip
    assert strip.size >= 5 and np.all(np.diff(strip) == 1), strip
    text = band.max(axis=2) < 60  # black text pixels
    dark = text.any(axis=1)
    above = np.flatnonzero(dark[: strip[0]])
    below = np.flatnonzero(dark[strip[-1] + 1 :])
    assert above.size >= 5 and below.size >= 5  # title above, tick labels below
    # Nothing touches: a gap between title and strip, and no text over the strip.
    assert strip[0] - above.max() >= 2
    assert text[strip].mean() < 0.002


def test_views_have_a_scale_bar_and_an_orientation_triad(cylinder_view: np.ndarray) -> None:
    img = cylinder_view.astype(int)
    h, w, _ = img.shape
    # Scale bar: a long dark horizontal line in the lower right corner.
    corner = img[int(0.8 * h) :, int(0.7 * w) :]
    dark_rows = (corner.max(axis=2) < 80).sum(axis=1)
    assert dark_rows.max() > 0.05 * w
    # Orientation triad: red, green and blue axes in the lower left corner.
    ll = img[int(0.7 * h) :, : int(0.15 * w)]
    r, g, b = ll[..., 0], ll[..., 1], ll[..., 2]
    seen = [
        ((r > 150) & (g < 140) & (b < 140)).any(),  # x
        ((g > 120) & (r < 120) & (b < 160)).any(),  # y
        ((b > 150) & (r < 100) & (g < 120)).any(),  # z
    ]
    assert sum(seen) >= 2, seen  # one axis may point at the viewer


def test_scale_bar_length_is_true_in_millimetres() -> None:
    import pyvista as pv

    render.use_offscreen_backend()
    pl = pv.Plotter(off_screen=True, window_size=[600, 400])
    try:
        pl.add_mesh(pv.Sphere(radius=10.0))
        pl.camera.parallel_projection = True
        pl.camera.parallel_scale = 20.0  # 40 mm over 400 px: 0.1 mm per pixel
        length = render.add_scale_bar(pl)
    finally:
        pl.close()
    assert length == render.nice_length(0.15 * 600 * 0.1) == 5.0


# -- overlays -------------------------------------------------------------------------
LONG = "frame 27 REJECTED: jump of 4.5 mm from neighbouring frames, and more words here"


@pytest.mark.parametrize("width", [64, 160, 320, 820])
def test_overlay_banner_wraps_within_the_frame(width: int) -> None:
    from PIL import ImageFont

    size = label_font_size(width)
    lines = label_lines(LONG, width - 8, size)
    font = ImageFont.load_default(size=size)
    assert all(font.getlength(line) <= width - 8 for line in lines)
    assert 1 <= len(lines) <= 3
    if width >= 320:  # wide enough: every word is shown
        assert " ".join(lines).split() == LONG.split()
    img = np.asarray(
        overlay_image(np.full((48 * width // 64, width), 128, np.uint8), accepted=False, label=LONG)
    )
    red = (img[..., 0] > 200) & (img[..., 1] < 100)
    rows = np.flatnonzero(red.any(axis=1))
    assert rows.size and rows.max() < img.shape[0] // 3 + 4  # the text sits in the banner


def test_overlay_font_reads_on_large_frames_shown_small() -> None:
    # The report shows frames about 320 px wide: an 820 px frame's text stays >= 11 px.
    assert label_font_size(820) * 320 / 820 >= 11
    assert label_font_size(160) == 12


# -- Table I plot ---------------------------------------------------------------------
def test_table_plot_distance_axis_starts_at_zero(tmp_path: Path) -> None:
    fig = table_figure([(5, 0.25), (10, 0.26), (15, 0.24), (20, 0.23)])
    assert fig.axes[0].get_ylim()[0] == 0.0
    from BoneUSRecon.cli.table import write_table_plot

    write_table_plot([(5, 0.25), (10, 0.26)], tmp_path / "t.png", title="mine")
    from PIL import Image

    with Image.open(tmp_path / "t.png") as im:
        assert im.size[0] >= 400
