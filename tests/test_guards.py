"""Input guards of issue 24: nothing the user gave is lost, no empty file is left behind, and
every entry point refuses the same bad images."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import tifffile

from torch_stsdic.cli import main

FAST = ["--threads", "1", "--no-progress"]


def _run(capsys, *argv) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _one_line(code: int, err: str, *names: str) -> str:
    assert code != 0
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("stsdic: error: "), lines[0]
    assert "Traceback" not in err and "Errno" not in err, err
    for name in names:
        assert name in lines[0], (name, lines[0])
    return lines[0]


@pytest.fixture(scope="module")
def movie(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("movie")
    assert main(["synth", "--out", str(d), "--size", "61", "--frames", "6", "--noise", "1",
                 "--threads", "1"]) == 0  # fmt: skip
    return d / "movie.tif"


# ----------------------------------------------------------------------------------------
# 1. an output that is one of the inputs is refused, whatever the flags
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("flag", [[], ["--overwrite"], ["--resume"]])
def test_out_is_the_input_movie(capsys, movie, tmp_path, flag):
    mv = tmp_path / "movie.tif"
    shutil.copy(movie, mv)
    before = mv.read_bytes()
    code, _, err = _run(capsys, "run", mv, "--out", mv, *flag, *FAST)
    _one_line(code, err, "--out", "input")
    assert mv.read_bytes() == before
    assert not list(tmp_path.glob("*.partial"))


def test_out_is_a_frame_of_a_folder_or_a_side_file(capsys, movie, tmp_path):
    frames = tmp_path / "frames"
    frames.mkdir()
    stack = tifffile.imread(movie)
    for i, im in enumerate(stack):
        tifffile.imwrite(frames / f"f{i}.tif", im)
    target = frames / "f3.tif"
    before = target.read_bytes()
    for src in (frames, str(frames / "f*.tif")):
        code, _, err = _run(capsys, "run", src, "--out", target, "--overwrite", *FAST)
        _one_line(code, err, "f3.tif", "input")
        assert target.read_bytes() == before
    pts = tmp_path / "pts.csv"
    pts.write_text("x,y\n30,30\n")
    link = tmp_path / "link.csv"
    link.symlink_to(pts)  # another name of the same file
    code, _, err = _run(capsys, "run", movie, "--points", pts, "--out", link, "--overwrite", *FAST)
    _one_line(code, err, "--points")
    assert pts.read_text() == "x,y\n30,30\n"


# ----------------------------------------------------------------------------------------
# issue 22: --refine-reference on a short series (5-frame fit, 6 unknowns with the bias terms)
# ----------------------------------------------------------------------------------------

#: one trajectory of DIC Challenge sample 12 (t = 1..11 after the reference) whose 5-frame
#: quadratic fit with the two bias terms (6 unknowns) made numpy raise "Singular matrix"
_V12 = [-0.4167485535144806, -0.8465142250061035, -1.3896907567977905, -1.8493677377700806,
        -2.3968091011047363, -2.870800495147705, -3.406524658203125, -4.032723903656006,
        -4.640514850616455, -5.271877765655518, -5.341021537780762]
_U12 = [-0.0836915522813797, -0.14846517145633698, -0.25250983238220215, -0.3404434025287628,
        -0.3647645115852356, -0.3589475154876709, -0.36959344148635864, -0.3422011733055115,
        -0.34113770723342896, -0.41716256737709045, -0.3938934803009033]


def _short_biased_series(n: int = 40) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """11 frames of 40 points moving 0.45 px per frame with a sub-pixel bias, one of them the
    sample-12 trajectory above."""
    rng = np.random.default_rng(1)
    t = np.arange(1.0, 12.0)
    w = -0.45 * t[:, None] + rng.uniform(0, 1, n)
    v = w + 0.04 * np.sin(2 * np.pi * w) + rng.normal(0, 0.01, (11, n))
    u = 0.02 * t[:, None] + rng.normal(0, 0.01, (11, n))
    v[:, 0], u[:, 0] = _V12, _U12
    return t, {"u": u, "v": v}


def test_refine_fits_have_more_frames_than_unknowns(monkeypatch):
    from torch_stsdic.movie import refine

    t, ys = _short_biased_series()
    shapes = []
    real = refine._fit

    def spy(ts, n_poly, disp, y=None, **kw):
        out = real(ts, n_poly, disp, y, **kw)
        shapes.append((len(ts), out[1].shape[-1]))
        return out

    monkeypatch.setattr(refine, "_fit", spy)
    res = refine.fit_intercepts(t, ys)  # raised "Singular matrix" before the fix
    assert res.bias_terms
    assert all(np.isfinite(v).all() for v in res.values.values())
    assert (res.frames > 0).all()
    assert shapes and all(rows > unknowns for rows, unknowns in shapes), shapes


@pytest.mark.parametrize("overwrite", [False, True])
def test_failed_refine_pre_pass_leaves_no_empty_file(capsys, movie, tmp_path, monkeypatch,
                                                     overwrite):
    from torch_stsdic.movie import refine

    def broken(*a, **k):
        raise np.linalg.LinAlgError("Singular matrix")

    monkeypatch.setattr(refine, "fit_intercepts", broken)
    out = tmp_path / "r.h5"
    if overwrite:
        out.write_bytes(b"old result")
    extra = ["--overwrite"] if overwrite else []
    code, _, err = _run(capsys, "run", movie, "--subset", "15", "--step", "5",
                        "--refine-reference", "--out", out, *extra, *FAST)  # fmt: skip
    _one_line(code, err, "Singular matrix")
    assert sorted(p.name for p in tmp_path.iterdir()) == (["r.h5"] if overwrite else [])
    if overwrite:
        assert out.read_bytes() == b"old result"


# ----------------------------------------------------------------------------------------
# 2. a truncated TIFF is refused up front, in one line, and no result file is made
# ----------------------------------------------------------------------------------------


def _page_by_page(movie: Path, dst: Path) -> int:
    """The movie rewritten with each page's directory before its data; its size."""
    with tifffile.TiffWriter(dst) as w:
        for im in tifffile.imread(movie):
            w.write(im, contiguous=False)
    return dst.stat().st_size


@pytest.mark.parametrize("cut", ["last page's pixels", "page directories"])
def test_truncated_tiff_refused_before_any_output(capsys, movie, tmp_path, cut):
    full = tmp_path / "full.tif"
    size = _page_by_page(movie, full)
    keep = size - 2000 if cut == "last page's pixels" else size // 2
    bad = tmp_path / "cut.tif"
    bad.write_bytes(full.read_bytes()[:keep])
    out = tmp_path / "r.h5"
    code, _, err = _run(capsys, "run", bad, "--subset", "15", "--m", "1", "--out", out, *FAST)
    line = _one_line(code, err, "cut.tif", "truncated")
    assert "resume" not in line
    assert not out.exists() and not list(tmp_path.glob("r.h5*"))


@pytest.mark.parametrize("suffix", [".png", ".bmp"])
def test_truncated_png_or_bmp_frame_refused_before_any_output(capsys, movie, tmp_path, suffix):
    from PIL import Image

    frames = tmp_path / "frames"
    frames.mkdir()
    for i, im in enumerate(tifffile.imread(movie)):
        Image.fromarray(im).save(frames / f"f{i}{suffix}")
    victim = frames / f"f3{suffix}"
    victim.write_bytes(victim.read_bytes()[:-600])
    out = tmp_path / "r.h5"
    code, _, err = _run(capsys, "run", frames, "--subset", "15", "--m", "1", "--out", out, *FAST)
    _one_line(code, err, f"f3{suffix}", "truncated")
    assert not list(tmp_path.glob("r.h5*"))


# ----------------------------------------------------------------------------------------
# 3. the same image rules at every entry point: nn.STSDIC, solve_window, track / plan_run
# ----------------------------------------------------------------------------------------


def _spoil(kind: str, frames):
    import torch

    if kind == "bool":
        return frames > frames.mean()
    if kind == "complex":
        return frames.to(torch.complex64)
    out = frames.clone()
    out[1, 20, 20] = float(kind)  # "nan" or "inf"
    return out


def _entry(name: str, frames) -> None:
    import torch

    from torch_stsdic import DICConfig, plan_run, solve_window, track
    from torch_stsdic.nn import STSDIC

    cfg = DICConfig(subset_size=11, m=1)
    pts = torch.tensor([[20.0, 20.0], [24.0, 22.0]])
    if name == "nn.STSDIC":
        STSDIC(cfg)(frames[:1], frames[None], pts)
    elif name == "solve_window":
        solve_window(frames[0], frames, pts, cfg)
    elif name == "track":
        track(frames, points=pts, config=cfg, progress=False)
    else:  # an array reference given to plan_run
        plan_run(torch.rand(3, *frames.shape[1:]) * 100, reference=frames[1], points=pts,
                 config=cfg)


@pytest.mark.parametrize("kind", ["nan", "inf", "bool", "complex"])
@pytest.mark.parametrize("entry", ["nn.STSDIC", "solve_window", "track", "reference"])
def test_bad_pixels_refused_at_every_entry_point(entry, kind):
    import torch

    g = torch.Generator().manual_seed(0)
    frames = torch.rand(3, 40, 40, generator=g, dtype=torch.float64) * 200
    bad = _spoil(kind, frames)
    expected = TypeError if kind in ("bool", "complex") else ValueError
    if entry == "track" and kind in ("bool", "complex"):
        expected = (TypeError, ValueError)  # InputError (a ValueError) names the array
    with pytest.raises(expected) as info:
        _entry(entry, bad)
    msg = str(info.value)
    assert ("non-finite" in msg) if kind in ("nan", "inf") else ("real numbers" in msg), msg


# ----------------------------------------------------------------------------------------
# 4. a missing output folder is created (with its parents), as docs/cli.md says
# ----------------------------------------------------------------------------------------


def test_missing_output_folders_are_created_as_documented(capsys, movie, tmp_path):
    out = tmp_path / "a" / "b" / "r.h5"
    code, _, err = _run(capsys, "run", movie, "--subset", "15", "--step", "20", "--m", "1",
                        "--out", out, *FAST)  # fmt: skip
    assert code == 0, err
    assert out.is_file()
    code, _, err = _run(capsys, "export", out, "--out", tmp_path / "c" / "d")
    assert code == 0 and list((tmp_path / "c" / "d").glob("*.csv")), err
    doc = (Path(__file__).resolve().parents[1] / "docs" / "cli.md").read_text()
    assert "missing output folder** is refused" not in doc
    assert "A missing one is\n  created**" in doc


# ----------------------------------------------------------------------------------------
# 5. export, plot, synth, demo into a read-only folder: one line naming the folder
# ----------------------------------------------------------------------------------------


@pytest.fixture()
def read_only(tmp_path):
    """A read-only folder: chmod for a user, a read-only tmpfs for root (else skip)."""
    import os
    import subprocess
    import sys

    ro = tmp_path / "ro"
    ro.mkdir()
    if os.geteuid() != 0:
        ro.chmod(0o500)
        yield ro
        ro.chmod(0o700)
        return
    if sys.platform != "linux":
        pytest.skip("a read-only folder for root needs a Linux tmpfs")
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=64k", "tmpfs", str(ro)],
                       capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a read-only tmpfs here: {r.stderr.strip()}")
    try:
        yield ro
    finally:
        subprocess.run(["umount", str(ro)], check=False)


@pytest.fixture(scope="module")
def result(movie, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("run") / "r.h5"
    assert main(["run", str(movie), "--subset", "15", "--step", "20", "--m", "1", "--out",
                 str(out), *FAST]) == 0  # fmt: skip
    return out


@pytest.mark.parametrize("argv", [["export", "{r}", "--out", "{ro}/csv"],
                                  ["export", "{r}", "--format", "mat", "--out", "{ro}"],
                                  ["export", "{r}", "--out", "{ro}/f{{frame}}.csv"],
                                  ["plot", "{r}", "--out", "{ro}", "--no-image"],
                                  ["synth", "--out", "{ro}/mv", "--size", "32"]])
def test_read_only_output_folder_is_one_line(capsys, result, read_only, argv):
    args = [a.format(r=result, ro=read_only) for a in argv]
    code, _, err = _run(capsys, *args)
    assert code == 1
    _one_line(code, err, "not writable", str(read_only))
    assert not list(read_only.iterdir())


def test_os_errors_are_one_line_without_errno(capsys, result, tmp_path):
    (tmp_path / "r_frame00000.csv").mkdir()  # a folder where a CSV file goes
    code, _, err = _run(capsys, "export", result, "--out", tmp_path)
    _one_line(code, err, "r_frame00000.csv")


# ----------------------------------------------------------------------------------------
# 8. docs/cli.md's option table and summary of 'stsdic run' are made from the program
# ----------------------------------------------------------------------------------------


def _docs_script():
    from repo_scripts import load_script  # tests/ on the path

    return load_script("scripts/tools/regenerate_docs.py", "regenerate_docs_guards")


def test_cli_reference_is_generated_and_current():
    docs = _docs_script()
    text = docs.CLI_DOC.read_text(encoding="utf-8")
    assert docs.stale_cli(text) == []  # what `regenerate_docs.py --check --cli` runs
    table = docs.options_table("run")
    from torch_stsdic.cli.app import build_parser

    run_help = build_parser().parse_known_args(["run", "x", "--out", "y"])[0]
    flag = {"checks": "no-checks"}  # options whose flag is not their destination's name
    for dest in vars(run_help):
        if dest not in ("inputs", "command", "func", "debug"):
            assert f"`--{flag.get(dest, dest.replace('_', '-'))}" in table, dest
    i, j = docs._block(text, "run-options")
    assert docs.stale_cli(text[:i] + table.replace("| 21 |", "| 19 |") + text[j:])  # cached


# ----------------------------------------------------------------------------------------
# 7. plots: axes in the calibrated unit, diverging maps only for two-signed data, --point far
#    outside the points refused
# ----------------------------------------------------------------------------------------


def _grid(step: float = 10.0) -> np.ndarray:
    xs, ys = np.meshgrid(np.arange(20.0, 181.0, step), np.arange(20.0, 121.0, step))
    return np.column_stack([xs.ravel(), ys.ravel()])


def test_plot_axes_in_the_calibrated_unit():
    from torch_stsdic.io.units import Units
    from torch_stsdic.plot import plot_fields

    pts = _grid()
    fig = plot_fields(None, pts, {"u": pts[:, 0] * 0.01}, units=Units(scale=0.02, unit="mm"))
    ax = fig.axes[0]
    fig.canvas.draw()
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("x (mm)", "y (mm)")
    ticks = [float(t.get_text().replace("\N{MINUS SIGN}", "-")) for t in ax.get_xticklabels()
             if t.get_text()]
    assert ticks and all(abs(t * 2 - round(t * 2)) < 1e-9 for t in ticks), ticks  # round mm
    assert min(ticks) < 20 * 0.02 + 0.5 and max(ticks) > 180 * 0.02 - 0.5
    plain = plot_fields(None, pts, {"u": pts[:, 0]})
    assert plain.axes[0].get_xlabel() == "x (px)"


def _panel_cmap_and_limits(fig) -> tuple[str, float, float]:
    m = fig.axes[0].images[-1] if fig.axes[0].images else fig.axes[0].collections[-1]
    return m.get_cmap().name, float(m.norm.vmin), float(m.norm.vmax)


def test_one_signed_strain_uses_its_range():
    from torch_stsdic.plot import plot_fields

    pts = _grid()
    rng = np.random.default_rng(0)
    eyy = 0.004 + 0.001 * rng.standard_normal(len(pts))  # all > 0
    name, lo, hi = _panel_cmap_and_limits(plot_fields(None, pts, {"eyy": eyy}))
    assert name != "RdBu_r" and lo > 0 and hi < eyy.max() + 1e-12, (name, lo, hi)
    exy = 0.002 * rng.standard_normal(len(pts))  # both signs: diverging, centred on 0
    name, lo, hi = _panel_cmap_and_limits(plot_fields(None, pts, {"exy": exy}))
    assert name == "RdBu_r" and lo == -hi


def test_plot_point_far_outside_is_refused(capsys, result, tmp_path):
    code, _, err = _run(capsys, "plot", result, "--out", tmp_path / "p", "--point", "500",
                        "500", "--no-image")  # fmt: skip
    assert code == 2
    _one_line(code, err, "--point", "px away")
    assert not (tmp_path / "p").exists() or not list((tmp_path / "p").iterdir())
    code, _, err = _run(capsys, "plot", result, "--out", tmp_path / "q", "--point", "31",
                        "29", "--no-image")  # fmt: skip
    assert code == 0, err


# ----------------------------------------------------------------------------------------
# 6. README and docs say what a new user needs
# ----------------------------------------------------------------------------------------

ROOT = Path(__file__).resolve().parents[1]


def test_readme_quick_start_installs_cpu_torch_first():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    quick = text[text.index("## Quick start"):text.index("<!-- generated: demo-table -->")]
    venv, cpu = quick.find("python -m venv"), quick.find("download.pytorch.org/whl/cpu")
    assert 0 <= venv < cpu < quick.find("pip install . "), quick
    assert "torch==" in quick
    # the test command's time, as measured (with the date and the machine)
    assert "about 1 minute" not in text and "measured" in quick and " min " in quick
    assert "2 cores" in quick


def test_demo_output_folder_is_git_ignored():
    import subprocess

    r = subprocess.run(["git", "check-ignore", "-q", "stsdic-demo/fields.png"], cwd=ROOT,
                       capture_output=True)
    if r.returncode == 128:
        pytest.skip("not a git checkout")
    assert r.returncode == 0, ".gitignore does not ignore ./stsdic-demo"


def test_sample14_figure_says_it_is_column_averaged():
    text = (ROOT / "docs" / "validation.md").read_text(encoding="utf-8")
    i = text.index("![sample 14](validation/dic_challenge_sample14.png)")
    near = text[i - 1500:i + 400]
    assert "averag" in near and "0.022 px" in near, near
