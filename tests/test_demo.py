"""The demo experiment as a library function: its numbers against the exactly known motion."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from torch_stsdic.demo import UT_TRUE, DemoSettings, check_settings, run_demo


@pytest.fixture(scope="module")
def quick():
    """The quick demo at the paper's noise (sigma 5): 101 px, 7 frames, 9 points."""
    return run_demo(quick=True)


@pytest.fixture(scope="module")
def quick_stills():
    """The quick demo with the reference also averaged from 4 still frames."""
    return run_demo(quick=True, still_frames=4)


def test_settings_quick_and_defaults():
    assert DemoSettings.create() == DemoSettings()
    assert (DemoSettings().size, DemoSettings().frames, DemoSettings().noise) == (301, 9, 5.0)
    q = DemoSettings.create(True)
    assert (q.size, q.frames, q.step, q.still_frames, q.refined) == (101, 7, 25, 0, False)
    # None keeps the (quick) default, a value replaces it
    assert DemoSettings.create(True, size=None, still_frames=3) == DemoSettings(
        size=101, frames=7, step=25, still_frames=3, refined=False
    )


def test_truth_is_the_papers_translation(quick):
    s = quick.settings
    assert quick.times.tolist() == list(range(1, s.frames + 1))
    assert quick.points.shape == (9, 2)
    np.testing.assert_allclose(quick.u_true, UT_TRUE * quick.times[:, None] * np.ones((1, 9)))
    np.testing.assert_allclose(quick.v_true, 0.0)
    for r in quick.methods:
        np.testing.assert_allclose(r.error_u, r.u - quick.u_true)


def test_sts_beats_classical_at_noise_5(quick):
    c, s = quick.classical, quick.sts
    assert [r.method for r in quick.methods] == ["classical DIC", "STS-DIC"]
    assert (c.m, s.m) == (0, 2)
    assert c.valid_percent == s.valid_percent == 100.0
    # noise 5 gives errors of a few hundredths of a pixel, not zero and not gross
    for r in (c, s):
        assert 0.005 < r.rms_u < 0.05 and 0.005 < r.rms_v < 0.05
    assert s.rms_u < c.rms_u and s.rms_v < c.rms_v
    # the velocity: STS-DIC measures it; finite differences of classical u are >2x worse
    assert c.ut_from_finite_differences and not s.ut_from_finite_differences
    # measured 4.47 (README's full demo: 3.1; seeds 0-5 of the quick demo: 2.6-4.5)
    assert 3.5 < c.rms_ut / s.rms_ut < 5.5
    # one noisy reference bounds the expected gain in u near 1 / sqrt((1 + 1/5) / 2) = 1.29;
    # measured 1.18 (u) and 1.21 (v) for this seed; bands 1.1..1.3 (9 points: other seeds
    # give 1.18-1.58, so this pins the computation of seed 0, deterministic)
    ratios = quick.ratios()
    assert 1.1 < ratios["u"] < 1.3 and 1.1 < ratios["v"] < 1.3, ratios
    assert ratios["ut"] == pytest.approx(c.rms_ut / s.rms_ut)


def test_per_frame_numbers_are_consistent(quick):
    for r in quick.methods:
        per_frame = np.asarray(r.rms_u_per_frame)
        assert per_frame.shape == (quick.settings.frames,)
        assert math.sqrt(np.mean(per_frame**2)) == pytest.approx(r.rms_u, rel=1e-12)
        assert r.bias_u == pytest.approx(float(np.mean(r.error_u)))
        np.testing.assert_allclose(r.mean_u_per_frame, r.u.mean(axis=1))
        assert r.time_s > 0 and r.poi_per_s == pytest.approx(r.u.size / r.time_s)


def test_noise_free_movie_is_measured_exactly():
    d = run_demo(quick=True, noise=0.0)
    for r in d.methods:
        assert r.rms_u < 2e-3 and r.rms_v < 2e-3 and r.rms_ut < 2e-3, r.summary()


def test_averaged_reference_lowers_the_error(quick_stills):
    rows = quick_stills.methods
    assert [r.method for r in rows[2:]] == [
        "classical DIC, ref=mean of 4",
        "STS-DIC, ref=mean of 4",
    ]
    assert rows[2].rms_u < rows[0].rms_u  # classical: averaged vs single reference
    assert rows[3].rms_u < rows[1].rms_u  # STS-DIC
    # STS + averaged reference vs classical: README 0.42x (full demo, 8 stills); measured
    # 0.46 here (4 stills); band 0.38..0.55
    assert 0.38 < rows[3].rms_u / rows[0].rms_u < 0.55
    table = quick_stills.table()
    assert "ref=mean of 4" in table and "1 / sqrt((1 + 1/5) / 2) = 1.29x" in table
    _assert_ratios_under_their_columns(table)


def _assert_ratios_under_their_columns(table: str) -> None:
    """Every ratio line puts its u, v, ut ratios so that each 'x' stands where the last digit
    of the u, v and ut error columns is (the issue: 'ratio lines stand under no column')."""
    lines = table.splitlines()
    row = lines[4]  # the first method's row
    ends = [row.index(tok) + len(tok.rstrip("*")) for tok in row.split()[-6:-3]]  # u, v, ut
    ratios = [ln for ln in lines if ln.rstrip().endswith("x") and "ratio" in ln or
              ln.startswith("classical / STS-DIC ref")]  # fmt: skip
    assert ratios
    for ln in ratios:
        xs = [i + 1 for i, ch in enumerate(ln) if ch == "x" and ln[i - 1].isdigit()]
        assert xs == ends, (ln, row)


def test_table_and_header(quick):
    lines = quick.table().splitlines()
    assert "RMS u err" in lines[1] and "POI/s" in lines[1]
    row = lines[4].split()
    assert row[:3] == ["classical", "DIC", "0"]
    assert float(row[3]) == pytest.approx(quick.classical.rms_u, abs=5e-5)
    assert row[5] == f"{quick.classical.rms_ut:.4f}*"  # finite differences are starred
    assert lines[-1].startswith("* classical DIC measures no velocity")
    assert "9 points" in quick.header() and "101x101 px" in quick.header()
    assert "noise sigma 5 grey levels" in quick.header()
    _assert_ratios_under_their_columns(quick.table())


def test_figures_show_errors_on_shared_diverging_scales(quick):
    """fields.png: error maps of u and ut (no repeated row), each row on one colour scale
    centred on 0 with the unit in the colour bar; history.png: errors, one column per method."""
    from torch_stsdic.demo import _fields_figure, _history_figure

    fig = _fields_figure(quick, np.zeros((101, 101)), None)
    panels = [ax for ax in fig.axes if ax.child_axes]
    titles = [ax.get_title() for ax in panels]
    assert titles == ["u error, classical DIC", "u error, STS-DIC m=2",
                      "ut error, classical DIC (finite diff.)", "ut error, STS-DIC m=2"]
    norms = [ax.images[-1].norm for ax in panels]
    assert (norms[0].vmin, norms[0].vmax) == (norms[1].vmin, norms[1].vmax)
    assert (norms[2].vmin, norms[2].vmax) == (norms[3].vmin, norms[3].vmax)
    for n in norms:
        assert n.vmin == pytest.approx(-n.vmax) and n.vmax > 0
    labels = [ax.child_axes[0].get_ylabel() for ax in panels]
    assert labels == ["u error (px)"] * 2 + ["ut error (px/frame)"] * 2
    hist = _history_figure(quick, None)
    assert len(hist.axes) == 2 * len(quick.methods)
    assert hist.axes[0].get_ylabel() == "u error (px)"


def test_files_and_json(tmp_path):
    said = []
    d = run_demo(tmp_path / "out", quick=True, log=said.append)
    assert said == [d.header()]
    names = [p.name for p in d.files]
    assert names == ["error_per_frame.png", "fields.png", "history.png", "demo.json"]
    for p in d.files[:3]:
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and p.stat().st_size > 5000
    saved = json.loads(d.files[3].read_text())
    assert saved["settings"]["points"] == 9 and saved["settings"]["still_frames"] == 0
    assert [r["rms_u"] for r in saved["results"]] == [r.rms_u for r in d.methods]
    assert saved["ratio_classical_over_sts"]["u"] == d.ratios()["u"]
    assert "u" not in saved["results"][0]  # numbers only, no arrays


def test_no_folder_writes_nothing(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    d = run_demo(quick=True)
    assert d.files == [] and not list(tmp_path.iterdir())


@pytest.mark.parametrize(
    ("changes", "words"),
    [
        ({"frames": 4}, ["frames 4", "m 2", "at least 5 frames"]),
        ({"subset": 121}, ["subset 121", "101 px"]),
        ({"size": 41, "subset": 41}, ["size 41", "too small"]),
        ({"m": 0}, ["m 0", ">= 1"]),
    ],
)
def test_bad_settings(changes, words):
    s = DemoSettings.create(True, **changes)
    with pytest.raises(ValueError) as exc:
        check_settings(s)
    for w in words:
        assert w in str(exc.value)
    with pytest.raises(ValueError, match=words[0].split()[0]):
        run_demo(quick=True, **changes)
    with pytest.raises(ValueError, match="--" + words[0].split()[0]):
        check_settings(s, name=lambda k: "--" + k)


def test_refined_reference_row():
    d = run_demo(quick=True, refined=True, frames=9)
    assert [r.method for r in d.methods] == ["classical DIC", "STS-DIC", "STS-DIC, refined ref"]
    refined = d.methods[2]
    assert refined.valid_percent == 100.0
    assert refined.rms_u < d.methods[1].rms_u  # the reference's offset fitted away
    # README: 0.49x classical with 10 images; measured 0.54 here (9 points); band 0.42..0.65
    assert 0.42 < refined.rms_u / d.methods[0].rms_u < 0.65
    assert "STS-DIC refined ref" in d.table()


def _docs_script():
    from repo_scripts import load_script  # tests/ on the path

    return load_script("scripts/tools/regenerate_docs.py", "regenerate_docs")


def test_docs_quote_the_program():
    """docs/cli.md pastes 'stsdic --help' as it is now, and the README, docs/cli.md and
    'stsdic --help' all quote the same demo time (scripts/tools/regenerate_docs.py --check)."""
    docs = _docs_script()
    text = docs.CLI_DOC.read_text(encoding="utf-8")
    assert docs.stale(text, demo=False) == []
    # a stale paste is reported
    i, j = docs._block(text, "help")
    assert docs.stale(text[:i] + "```\nold help\n```\n" + text[j:], demo=False)


@pytest.mark.slow
def test_docs_paste_a_real_demo_run():
    """The demo block of docs/cli.md has the numbers a run gives now (times excepted)."""
    docs = _docs_script()
    assert docs.stale(docs.CLI_DOC.read_text(encoding="utf-8")) == []
