"""The report stage: report.md unchanged by the HTML work, and report.html self-contained and complete.

The fixture ``tests/fixtures/eval/`` is a real tiny-profile evaluation (every family's metrics.json,
real/meta.json) with the report.md the stage wrote from it. report.html is checked by parsing it with
the standard library (every table cell as in report.md, every image decoding to its file's bytes and
size, nothing external) and, where Debian's chromium is installed, by a headless screenshot.
"""

from __future__ import annotations

import base64
import io
import json
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import pytest
from PIL import Image

from pipelines.report import merge_tables, report_markdown, report_sections, report_title, table_cells
from pipelines.report_html import report_html
from stages import report as report_stage

FIXTURE = Path(__file__).parent / "fixtures" / "eval"
SAMPLE_ROWS = {"mld": "MLD-DDIM50", "emdm": "EMDM-10"}
SAMPLE_SIZE = (40, 30)
SAMPLE_COLOUR = (200, 30, 160)  # in no other part of the page: counted in the screenshot


class PageParser(HTMLParser):
    """The page's tables (rows of cell texts), images (attributes) and every tag name used."""

    def __init__(self) -> None:
        super().__init__()
        self.tables: list[list[list[str]]] = []
        self.images: list[dict[str, str]] = []
        self.tags: set[str] = set()
        self.urls: list[str] = []
        self._cell: list[str] | None = None

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.tags.add(tag)
        values = {name: value or "" for name, value in attrs}
        self.urls += [values[name] for name in ("src", "href") if name in values]
        if tag == "table":
            self.tables.append([])
        elif tag == "tr":
            self.tables[-1].append([])
        elif tag in ("td", "th"):
            self._cell = []
        elif tag == "img":
            self.images.append(values)

    def handle_endtag(self, tag: str) -> None:
        if tag in ("td", "th"):
            self.tables[-1][-1].append("".join(self._cell))
            self._cell = None

    def handle_data(self, data: str) -> None:
        if self._cell is not None:
            self._cell.append(data)


def markdown_tables(text: str) -> list[list[list[str]]]:
    """report.md's tables as rows of cell texts (the |---| line left out)."""
    tables: list[list[list[str]]] = []
    previous = ""
    for line in text.splitlines():
        if line.startswith("|") and not line.startswith("|---"):
            if not previous.startswith("|"):
                tables.append([])
            tables[-1].append([cell.strip() for cell in line.strip("|").split("|")])
        previous = line
    return tables


def _gif(path: Path, colour: tuple[int, int, int]) -> None:
    """Two frames of ``colour``, the second with a white 4x4 corner: whichever frame a browser shows,
    all but 16 pixels have the colour."""
    frames = [Image.new("RGB", SAMPLE_SIZE, colour), Image.new("RGB", SAMPLE_SIZE, colour)]
    frames[1].paste((255, 255, 255), (0, 0, 4, 4))
    frames[0].save(path, save_all=True, append_images=frames[1:], duration=100, loop=0)


@pytest.fixture()
def artifacts(tmp_path: Path) -> Path:
    """An artifacts/ tree with the fixture's evaluation outputs and two GIFs per sampled row."""
    shutil.copytree(FIXTURE, tmp_path / "eval", ignore=shutil.ignore_patterns("report.md"))
    for family, row in SAMPLE_ROWS.items():
        (tmp_path / "eval" / family / "samples").mkdir()
        for k in range(2):
            _gif(tmp_path / "eval" / family / "samples" / f"{row}_{k}.gif", SAMPLE_COLOUR)
    return tmp_path


def _run_stage(artifacts: Path) -> Path:
    report_stage.run({"paths": {"artifacts": str(artifacts)}})
    return artifacts / "eval"


def test_report_markdown_is_the_real_runs_report() -> None:
    """Splitting report_markdown into sections for the HTML page left its output byte for byte."""
    tables = [json.loads((FIXTURE / name / "metrics.json").read_text()) for name in report_stage.SOURCES]
    meta = json.loads((FIXTURE / "real" / "meta.json").read_text())
    speed = json.loads((FIXTURE / report_stage.SPEED / "metrics.json").read_text())
    assert report_markdown(merge_tables(tables), meta, speed) == (FIXTURE / "report.md").read_text(encoding="utf-8")


def test_the_title_names_the_gpu_the_networks_ran_on() -> None:
    meta = json.loads((FIXTURE / "real" / "meta.json").read_text())
    assert report_title(meta) == "Evaluation on synthetic (452 test items, 3 replications)"
    assert report_title(meta | {"device": "cpu"}) == report_title(meta)
    assert report_title(meta | {"device": "cuda NVIDIA H100"}) == (
        "Evaluation on synthetic (452 test items, 3 replications, networks on cuda NVIDIA H100)")


def test_the_speed_table_comes_last_with_its_columns_and_only_when_it_has_rows() -> None:
    table = {"Real": {"R_precision_top3": 0.9, "FID": 0.0}}
    speed = {"EMDM-10": {"ms_per_frame": 0.5, "AITS_s": 0.05, "NFE": 20.0, "params_M": 1.23, "speedup": 120.4},
             "MotionDiffuse-1000": {"ms_per_frame": 60.2, "AITS_s": 7.2, "NFE": 1000.0, "params_M": 1.4,
                                    "speedup": 1.0}}
    last = report_sections(table, speed)[-1]
    assert last.heading.startswith("Inference speed side by side") and list(last.rows) == list(speed)
    header, rows = table_cells(last)
    assert header == ["Method", "ms/frame ↓", "AITS (s) ↓", "NFE", "Params (M)", "Speed-up ↑"]
    assert rows[0] == ["EMDM-10", "0.500", "0.0500", "20", "1.23", "120.4"]
    assert len(report_sections(table, {})) == len(report_sections(table)) == 1


def test_a_reconstructions_action_accuracy_goes_to_the_detail_table_not_the_paraphrase_table() -> None:
    table = {"Real": {"FID": 0.0, "action_accuracy": 0.96},
             "VAE": {"FID": 0.8, "path_err_m": 0.25, "action_accuracy": 0.79},
             "MLD": {"FID": 1.4, "action_accuracy": 0.62}, "MLD@paraphrase": {"FID": 17.0, "action_accuracy": 0.31}}
    sections = {(section.heading or "").split(" (")[0]: section for section in report_sections(table)}
    assert list(sections["Reconstruction detail"].rows) == ["VAE"]
    assert ("action_accuracy", "Action acc. ↑", 3) in sections["Reconstruction detail"].columns
    assert list(sections["Held-out paraphrases"].rows) == ["Real", "MLD", "MLD@paraphrase"]


def test_report_html_has_every_table_cell_of_report_md(artifacts: Path) -> None:
    eval_dir = _run_stage(artifacts)
    page = PageParser()
    page.feed((eval_dir / "report.html").read_text(encoding="utf-8"))
    expected = markdown_tables((eval_dir / "report.md").read_text(encoding="utf-8"))
    # text, detail, control, paraphrase, action, speed
    assert [len(table) for table in expected] == [19, 2, 5, 10, 3, 3]
    assert page.tables == expected


def test_report_html_embeds_plot_and_samples_and_loads_nothing(artifacts: Path) -> None:
    eval_dir = _run_stage(artifacts)
    page = PageParser()
    page.feed((eval_dir / "report.html").read_text(encoding="utf-8"))
    assert not {"script", "link", "iframe", "object", "embed"} & page.tags
    assert all(url.startswith("data:image/") for url in page.urls), [url[:40] for url in page.urls]
    # the plot, then the samples: families in the stage's order (mld before emdm), files sorted
    files = [eval_dir / "fid_vs_time.png", *sorted((eval_dir / "mld" / "samples").glob("*")),
             *sorted((eval_dir / "emdm" / "samples").glob("*"))]
    assert len(page.images) == len(files) == 5
    for image, path in zip(page.images, files, strict=True):
        data = base64.b64decode(image["src"].split(",", 1)[1])
        assert data == path.read_bytes(), path.name
        size = Image.open(io.BytesIO(data)).size
        assert (int(image["width"]), int(image["height"])) == size
    assert size == SAMPLE_SIZE


def test_report_html_is_deterministic(artifacts: Path) -> None:
    first = _run_stage(artifacts).joinpath("report.html").read_bytes()
    assert _run_stage(artifacts).joinpath("report.html").read_bytes() == first


def test_report_html_refuses_a_sample_it_cannot_embed() -> None:
    plot = io.BytesIO()
    Image.new("RGB", (4, 3)).save(plot, format="PNG")
    with pytest.raises(ValueError) as err:
        report_html({}, {"dataset": "d", "test_items": 1, "replications": 1}, plot.getvalue(), [("MLD_0.mp4", b"")])
    assert str(err.value) == "MLD_0.mp4: cannot embed in report.html (known image types: .gif, .png)"


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-headless-shell")


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed (apt-get install chromium)")
def test_report_html_renders_in_headless_chromium(artifacts: Path, tmp_path: Path) -> None:
    """The page as a browser draws it: not blank, with the tables' header cells, the plot's points and
    every sample animation's pixels on screen."""
    eval_dir = _run_stage(artifacts)
    shot = tmp_path / "shot.png"
    width, height = 1800, 3000
    proc = subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                           "--force-device-scale-factor=1", f"--window-size={width},{height}",
                           f"--screenshot={shot}", (eval_dir / "report.html").as_uri()],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and shot.is_file(), proc.stderr[-2000:]
    image = Image.open(shot).convert("RGB")
    assert image.size == (width, height)
    counts = {colour: n for n, colour in image.getcolors(maxcolors=width * height)}
    assert len(counts) > 50  # text, table, plot and animations: far from a blank page
    assert counts.get((238, 238, 238), 0) > 5000  # th background: the three tables' header rows
    plot = Image.open(eval_dir / "fid_vs_time.png").convert("RGB")
    points = [(colour, n) for n, colour in plot.getcolors(maxcolors=plot.width * plot.height)
              if max(colour) - min(colour) > 100]  # the scatter points' saturated colours
    assert len(points) >= 5
    assert all(counts.get(colour, 0) >= n for colour, n in points), points
    samples = len(SAMPLE_ROWS) * 2
    assert samples * (SAMPLE_SIZE[0] * SAMPLE_SIZE[1] - 16) <= counts.get(SAMPLE_COLOUR, 0) \
        <= samples * SAMPLE_SIZE[0] * SAMPLE_SIZE[1]


def test_paraphrase_twins_leave_the_papers_table_for_their_own() -> None:
    from pipelines import evaluation
    from pipelines.report import PARAPHRASE, report_sections

    assert PARAPHRASE == evaluation.PARAPHRASE
    row = {"R_precision_top3": 0.9, "FID": 1.0}
    table = {"Real": {**row, "action_accuracy": 0.97}, "MLD-DDIM50": {**row, "action_accuracy": 0.8},
             "MLD-DDIM50@paraphrase": {**row, "action_accuracy": 0.3}, "MLD-DDIM1": row}
    main, paraphrases = report_sections(table)
    assert list(main.rows) == ["Real", "MLD-DDIM50", "MLD-DDIM1"]
    assert list(paraphrases.rows) == ["Real", "MLD-DDIM50", "MLD-DDIM50@paraphrase"]
    assert "action_accuracy" in [key for key, _, _ in paraphrases.columns]
    assert len(report_sections({k: v for k, v in table.items() if not k.endswith(PARAPHRASE)})) == 1


def test_rows_evaluated_on_a_subset_are_marked() -> None:
    """A row bounded in captions, in replications or in both carries the mark the notes explain."""
    from pipelines.report import _name, report_notes

    assert _name("A", {"FID": 1.0}) == "A"
    assert _name("A", {"eval_items": 32.0}) == "A (†32)"
    assert _name("A", {"eval_items": 32.0, "eval_replications": 1.0}) == "A (†32, 1 rep.)"
    assert _name("A", {"eval_replications": 1.0}) == "A (1 rep.)"
    assert report_notes({"A": {"eval_replications": 1.0}})[-1].startswith("(R rep.), (†K, R rep.):")


@pytest.mark.parametrize(("text", "problem"), [
    ("[]", "expected {row: {metric: number}}"),
    ('{"EMDM-10": "x"}', "expected {row: {metric: number}}"),
    ('{"EMDM-10": {"FID": NaN}}', "EMDM-10: FID is nan, not a finite number"),
    ('{"EMDM-10": {"FID": "abc"}}', "EMDM-10: FID is 'abc', not a finite number"),
])
def test_a_bad_metrics_file_is_named_and_the_old_report_stays(artifacts: Path, text: str, problem: str) -> None:
    """A table that is not rows of finite numbers was dropped, shown as "–" or written as NaN into summary.json."""
    report_stage.run({"paths": {"artifacts": str(artifacts)}})
    before = {name: (artifacts / "eval" / name).read_bytes() for name in report_stage.OUTPUTS}
    bad = artifacts / "eval" / "emdm" / "metrics.json"
    bad.write_text(text)
    with pytest.raises(ValueError) as err:
        report_stage.run({"paths": {"artifacts": str(artifacts)}})
    assert str(err.value) == f"{bad}: {problem}; run `dvc repro eval_emdm` to write it again"
    assert {name: (artifacts / "eval" / name).read_bytes() for name in report_stage.OUTPUTS} == before


def test_a_folder_where_the_report_writes_a_file_stops_it_before_any_write(artifacts: Path) -> None:
    (artifacts / "eval" / "report.html").mkdir()
    with pytest.raises(ValueError, match=r"report.html is a directory, where the report writes a file"):
        report_stage.run({"paths": {"artifacts": str(artifacts)}})
    assert not (artifacts / "eval" / "metrics.json").exists() and not (artifacts / "eval" / "report.md").exists()


def test_a_family_scored_with_other_settings_than_real_is_refused(artifacts: Path) -> None:
    """``python -m stages.evaluate emdm evaluate.mm_times=2`` by hand, or Real scored again on another split:
    the report put both protocols' figures in one table. It names the folder, each setting that differs
    and the command; the old report stays."""
    report_stage.run({"paths": {"artifacts": str(artifacts)}})
    before = {name: (artifacts / "eval" / name).read_bytes() for name in report_stage.OUTPUTS}
    path = artifacts / "eval" / "emdm" / "protocol.json"
    protocol = json.loads(path.read_text())
    path.write_text(json.dumps(protocol | {"mm_times": 2, "test_items": 100}))
    with pytest.raises(ValueError) as err:
        report_stage.run({"paths": {"artifacts": str(artifacts)}})
    assert str(err.value) == (f"{path}: scored with another protocol than real (test_items 100 against 452; mm_times "
                              "2 against 10): run `dvc repro eval_emdm` to score it again with the same settings")
    assert {name: (artifacts / "eval" / name).read_bytes() for name in report_stage.OUTPUTS} == before
    path.write_text(json.dumps(protocol | {"device": "cuda NVIDIA H100"}))  # sample.device: its numbers differ too
    with pytest.raises(ValueError, match=r"emdm/protocol.json: scored with another protocol than real \(device "
                                         r"'cuda NVIDIA H100' against 'cpu'\)"):
        report_stage.run({"paths": {"artifacts": str(artifacts)}})
    (artifacts / "eval" / "emdm" / "metrics.json").write_text("{}\n")  # trained nothing: no rows to mix
    report_stage.run({"paths": {"artifacts": str(artifacts)}})
    path.write_text(json.dumps(protocol))
    (artifacts / "eval" / "speed" / "protocol.json").unlink()  # written before the stages wrote their protocol
    with pytest.raises(FileNotFoundError, match=r"speed/protocol.json is missing: run `dvc repro eval_speed` first"):
        report_stage.run({"paths": {"artifacts": str(artifacts)}})
