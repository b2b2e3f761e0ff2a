"""The reference made from the series (movie.series_reference): a template of the series'
images mapped back with their measured subset warps (smoothed by local planes) lowers the
error against known motion far below the single-reference floor, adds no sub-pixel bias,
fixes zero displacement by the reference frame's own measurement, and its predicted std
stays honest; it is on by default where it applies; bad combinations are refused."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torch_stsdic as sts
import torch_stsdic.movie.series_reference as series_reference
import torch_stsdic.movie.template_image as template_image
from torch_stsdic import synth
from torch_stsdic.analysis.local_fit import local_fit_weights

N_FRAMES = 17
MOTION = synth.QuadraticInTime(au=0.11, bu=-0.003, av=-0.06, bv=0.002)  # decelerating


@pytest.fixture(scope="module")
def movie():
    mv = synth.synthetic_movie((141, 141), N_FRAMES - 1, MOTION, noise_sigma=2.0, seed=7)
    series = torch.cat([mv.ref[None], mv.frames]).double()
    times = np.concatenate([[0.0], mv.times.numpy()])
    truth = [torch.tensor([MOTION._at(t)[i] for t in times], dtype=torch.float64)[:, None]
             for i in (0, 1)]
    return series, times, truth


def _run(movie, m, **kw):
    series, times, _ = movie
    kw = {"reference": 0, **kw}
    return sts.track(series, config=sts.DICConfig(m=m, subset_size=21), step=8, times=times,
                     progress=False, checks=False, shared_motion=None, **kw)


def _errors(res, truth):
    """RMS of the random error (each frame's mean error, the same at every point of this
    uniform motion: the time model's bias in a decelerating motion, taken out), RMS of the
    predicted std, the mean error."""
    e = torch.stack([res.u.double()[1:] - truth[0][1:], res.v.double()[1:] - truth[1][1:]])
    pred = torch.stack([res.std["u"].double()[1:], res.std["v"].double()[1:]])
    ok = torch.isfinite(e) & torch.isfinite(pred)
    e, pred = torch.where(ok, e, torch.nan), torch.where(ok, pred, torch.nan)
    rand = e - torch.nanmean(e, -1, keepdim=True)
    return float(torch.nanmean(rand ** 2).sqrt()), float(torch.nanmean(pred ** 2).sqrt()), \
        float(torch.nanmean(e))


@pytest.fixture(scope="module")
def runs(movie):
    return {"single": _run(movie, 0, series_reference=False),
            "series": _run(movie, 0),  # the default: on
            "sts_single": _run(movie, 2, series_reference=False),
            "sts_series": _run(movie, 2)}


def test_template_lowers_the_error_below_the_single_reference_floor(movie, runs):
    """Against image 0 STS-DIC m=2 cannot go below sqrt((1 + 1/5) / 2) = 0.77x classical
    DIC (the reference's noise is in every frame). Against the template of the 17 images
    classical DIC and STS m=2 go below it (measured in the docstring of the bands below)."""
    single = _errors(runs["single"], movie[2])[0]
    assert _errors(runs["sts_single"], movie[2])[0] >= 0.68 * single  # measured 0.74
    assert _errors(runs["series"], movie[2])[0] <= BAND_CLASSICAL * single
    assert _errors(runs["sts_series"], movie[2])[0] <= BAND_STS * single
    info = runs["series"].info["series_reference"]
    assert info["iterations"] == 2 and len(info["frames"]) == N_FRAMES
    assert info["coverage"] > 0.9 and info["plane_share"] > 0.9
    assert "single_reference" not in runs["series"].info
    assert runs["single"].info["single_reference"] == "asked for"


#: measured on this render (random error): classical 0.76x, STS m=2 0.41x (theory
#: sqrt((1/5 + 1/17) / 2) = 0.36 inside the movie, more at its ends)
BAND_CLASSICAL, BAND_STS = 0.85, 0.5


def test_reference_frame_reads_zero(runs):
    """The reference frame's row is the truth, 0 (and its std), where it was solved: the
    gauge (its own measurement against the template) fixes zero displacement."""
    for key in ("series", "sts_series"):
        res = runs[key]
        ok = res.status[0] <= 1
        assert bool(ok.all())
        assert float(res.u[0][ok].abs().max()) == 0.0 and float(res.v[0][ok].abs().max()) == 0.0
        assert float(res.std["u"][0][ok].abs().max()) == 0.0


def test_template_adds_no_bias(movie, runs):
    """The mean error (over points and frames: the sub-pixel bias of the motion's fractional
    positions) stays within 1e-3 px of the single reference's."""
    for single, series in (("single", "series"), ("sts_single", "sts_series")):
        _, _, b_single = _errors(runs[single], movie[2])
        _, _, b_series = _errors(runs[series], movie[2])
        assert abs(b_series - b_single) < 1e-3 and abs(b_series) < 2e-3, (b_single, b_series)


@pytest.mark.parametrize("key", ["series", "sts_series"])
def test_predicted_std_includes_the_template(movie, runs, key):
    """u_std / v_std against the template: measured / predicted error within 0.8-1.25
    (classical and STS m=2 on this render; sample 3 in docs/validation/series_reference.md)."""
    rms, pred, _ = _errors(runs[key], movie[2])
    assert 0.8 <= rms / pred <= 1.25, (rms, pred)


@pytest.mark.filterwarnings("ignore:refine_reference")
def test_default_follows_the_reference(movie):
    """"auto" (the default) measures against the template where the reference is a frame of
    the series, and says why not elsewhere."""
    series = movie[0]
    upd = _run(movie, 0, reference_update=0.9)
    assert "series_reference" not in upd.info
    assert "updated" in upd.info["single_reference"]
    ext = _run(movie, 0, reference=series[0].numpy())
    assert "series_reference" not in ext.info
    assert "not one frame" in ext.info["single_reference"]
    # the trajectories' gauge is a setting of the template
    ref = _run(movie, 0, refine_reference=True)
    assert "series_reference" in ref.info and "refine_reference" in ref.info


def _bump(size: int):
    c = (size - 1) / 2

    def fn(x, y, t):
        b = (1 - torch.exp(-t / 8.0)) * torch.exp(-((x - c) ** 2 + (y - c) ** 2)
                                                  / (2 * 50.0 ** 2))
        return 0.002 * (x - c) * t / 16 + b, 0.5 * b - 0.02 * t
    return synth.Custom(fn)


def _relaxing(size: int) -> synth.Motion:
    c = (size - 1) / 2

    def fn(x, y, t):
        e = 0.004 * (1 - torch.exp(-t / 8.0))
        return (e * (x - c) + 0.03 * t + 0.2 * (1 - torch.exp(-t / 5.0)),
                -0.3 * e * (y - c) - 0.02 * t)
    return synth.Custom(fn)


def _movie_error(mot, size: int, n: int, seed: int):
    mv = synth.synthetic_movie((size, size), n - 1, mot, noise_sigma=2.0, seed=seed)
    series = torch.cat([mv.ref[None], mv.frames]).double()
    times = torch.cat([torch.zeros(1, dtype=torch.float64), mv.times])

    def err(m, **kw):
        res = sts.track(series, config=sts.DICConfig(m=m, subset_size=21), progress=False,
                        **kw)
        gt = synth.ground_truth(mot, res.points.double(), times)
        e = torch.stack([res.u.double()[1:] - gt["u"][1:], res.v.double()[1:] - gt["v"][1:]])
        return float(e[torch.isfinite(e)].pow(2).mean().sqrt())
    return err


def test_gauge_removes_a_biased_registration(monkeypatch):
    """A field the local planes cannot follow (a Gaussian bump of 1 px, sigma 50 px) biases
    the template's registration; the reference frame's measurement against the template
    sees that bias and removes it (measured in GAUGE_GAIN's comment)."""
    err = _movie_error(_bump(201), 201, 17, 11)
    with_gauge = err(2)
    orig = series_reference._gauge

    def no_gauge(*a, **k):
        off, left = orig(*a, **k)
        off.values = {nm: np.zeros_like(v) for nm, v in off.values.items()}
        return off, left
    monkeypatch.setattr(series_reference, "_gauge", no_gauge)
    without = err(2)
    assert with_gauge <= GAUGE_GAIN * without, (with_gauge, without)


#: the gauge's gain on the bump render (with / without): measured 0.44 (STS m=2 with the
#: gauge 0.74x classical single-reference DIC, without it 1.68x); band 0.7
GAUGE_GAIN = 0.7


def test_relaxing_render_goal():
    """The issue's goal: a render whose motion is smooth but not linear in time (a stretch
    relaxing to 0.4 %, a decelerating drift), noise on every image, 31 frames: STS m=2 with
    defaults <= 0.45x classical DIC against the single reference image (measured 0.42x here,
    STS against the single reference 0.77x; 0.40x on the 301 px render of
    scripts/validation/series_reference_floor.py)."""
    err = _movie_error(_relaxing(201), 201, 31, 3)
    classical = err(0, series_reference=False)
    assert err(2) <= 0.45 * classical


@pytest.mark.parametrize("kw, match", [
    (dict(series_reference=False, refine_reference=True), "refine_reference: sets the gauge"),
    (dict(series_reference=True, reference_update=0.9), "reference_update"),
    (dict(series_reference=0.5), "iterations"),
    (dict(series_reference=False, series_frames=5), "series_frames: only with"),
    (dict(reference_update=0.9, series_frames=5), "does not apply here"),
    (dict(series_reference="always"), "series_reference"),
    (dict(series_reference=True, series_frames=1), "series_frames"),
])
def test_bad_combinations_are_refused(movie, kw, match):
    with pytest.raises(ValueError, match=match):
        _run(movie, 0, **kw)


def test_killed_run_resumes_to_the_same_result(movie, tmp_path):
    """A run against the template stopped after its first blocks, then resumed: the template
    is made again the same way (the same frames, the same warps), so the resumed file equals
    the uninterrupted one bit for bit."""
    from torch_stsdic.io import read_results

    class Crash(Exception):
        pass

    def crash(done, total):
        if done >= 6:
            raise Crash

    full = _run(movie, 2, out=tmp_path / "full.h5", batch_frames=3)
    with pytest.raises(Crash):
        _run(movie, 2, out=tmp_path / "cut.h5", batch_frames=3, callback=crash)
    part = read_results(tmp_path / "cut.h5")
    assert 0 < int(part.completed.sum()) < N_FRAMES
    res = _run(movie, 2, out=tmp_path / "cut.h5", batch_frames=3, resume=True)
    assert "series_reference" in full.info and "series_reference" in res.info
    a, b = read_results(tmp_path / "full.h5"), read_results(tmp_path / "cut.h5")
    for name in a.fields:
        assert np.array_equal(a.fields[name], b.fields[name], equal_nan=True), name
    # the file records the template the run measured against, with its summary
    img, attrs = b.arrays["series_reference"]
    assert img.shape == movie[0].shape[1:] and attrs["iterations"] == 2
    assert np.array_equal(img, a.arrays["series_reference"][0])


def test_series_template_feeds_the_differentiable_solver(movie):
    """Tensors in, tensors out: the template of the series (``series_template``) as the
    reference of ``nn.STSDIC``, its gauge subtracted, gives the displacements of ``track``
    against the same template (measured within 1.1e-4 px over frames 2-14) and beats the
    single reference image as nn.STSDIC's ``ref`` (0.63x its error there, the time model's
    bias of this decelerating motion included)."""
    from torch_stsdic.nn import STSDIC

    series, times, truth = movie
    res = _run(movie, 2)
    tmpl = sts.series_template(series, res.points, config=sts.DICConfig(m=2, subset_size=21))
    assert tmpl.image.shape == series.shape[1:] and tmpl.gauge is not None
    model = STSDIC(sts.DICConfig(m=2, subset_size=21))
    k = 8  # the window 6..10 about frame 8
    frames = series[k - 2:k + 3][None]
    gauge = torch.stack([torch.as_tensor(tmpl.gauge.values["u"]),
                         torch.as_tensor(tmpl.gauge.values["v"])], -1)
    out = model(tmpl.image[None], frames, res.points.double()) - gauge[None]
    single = model(series[0][None], frames, res.points.double())
    t = torch.stack([truth[0][k], truth[1][k]], -1)  # (1, 2)
    tracked = torch.stack([res.u[k], res.v[k]], -1)
    assert float((out[0] - tracked).abs().max()) < 1e-3
    err_t = float((out[0] - t).pow(2).mean().sqrt())
    err_s = float((single[0] - t).pow(2).mean().sqrt())
    assert err_t < 0.8 * err_s, (err_t, err_s)
    with pytest.raises(ValueError, match="rounds"):
        sts.series_template(series, res.points, rounds=0)


def test_the_template_made_frame_by_frame_equals_the_one_made_in_batches(movie, monkeypatch):
    """On the CPU the template's frames are splatted one by one, on a GPU in groups (one
    stack of coefficients, FrameCache.in_ring): the same template either way."""
    series, _, _ = movie
    res = _run(movie, 2)
    kw = dict(config=sts.DICConfig(m=2, subset_size=21), rounds=1)
    one = sts.series_template(series, res.points, **kw)
    groups, sizes = template_image.frame_groups, []
    monkeypatch.setattr(template_image, "frame_groups", lambda f, p, batched=True: [
        list(range(a, min(a + 5, f))) for a in range(0, f, 5)])  # groups of 5 frames
    take = template_image._group_frames
    monkeypatch.setattr(template_image, "_group_frames",
                        lambda cache, frames, dev, pixels=True: sizes.append(len(frames))
                        or take(cache, frames, dev, pixels))
    batched = sts.series_template(series, res.points, **kw)
    assert len(sizes) >= 2 and max(sizes) > 1 and sum(sizes) == len(one.frames), sizes
    torch.testing.assert_close(batched.image, one.image, rtol=0, atol=1e-9)
    assert abs(batched.noise_ratio - one.noise_ratio) < 1e-12
    # the groups' size: each frame's two float64 sums over the covered pixels in budget
    assert groups(10, 2**20 // 16, batched=False) == [[j] for j in range(10)]
    per = int(template_image._GROUP_MB)  # frames of 2**20 / 16 covered pixels in the budget
    assert [len(g) for g in groups(2 * per + 3, 2**20 // 16)] == [per, per, 3]


def _vibration(size: int) -> synth.Motion:
    """A vibration whose phase varies over the specimen (period 4 frames, 0.25 px): the
    affine-in-time window fits it nowhere, and no shared motion takes it out."""
    def fn(x, y, t):
        ph = (x + y) / 15.0
        a = 0.25 * (torch.sin(2 * np.pi * t / 4.0 + ph) - torch.sin(ph))
        return a, -0.5 * a
    return synth.Custom(fn)


def test_points_where_the_time_model_fails_are_solved_classically():
    """Decided once, from the template's classical measurement of the sampled frames: on a
    vibration the window cannot follow, most points are solved classically (no window, no
    check; measured 124 of 144 points here, 98 % of their usable rows classical, the rest
    rescued rows), their rows equal to a classical run's rows; on the relaxing render none
    is."""
    mv = synth.synthetic_movie((161, 161), 20, _vibration(161), noise_sigma=2.0, seed=1)
    series = torch.cat([mv.ref[None], mv.frames]).double()
    res = sts.track(series, config=sts.DICConfig(m=2), progress=False)
    info = res.info["series_reference"]
    cls = info["classical_points"]
    assert cls >= 0.4 * res.n_points, (cls, res.n_points)
    holds = sts.series_template(series, res.points, config=sts.DICConfig(m=2)).model_holds
    assert holds is not None and int((~holds).sum()) == cls
    rows = res.m[1:, ~holds][res.status[1:, ~holds] <= 1]
    share = float((rows == 0).double().mean())
    # the carried rows, and those a window solved first (the first block's FFT start, a
    # rescue) solved again classically (measured 100 %)
    assert share >= 0.99, share
    relax = synth.synthetic_movie((161, 161), 20, _relaxing(161), noise_sigma=2.0, seed=3)
    series = torch.cat([relax.ref[None], relax.frames]).double()
    res = sts.track(series, config=sts.DICConfig(m=2), progress=False)
    assert res.info["series_reference"]["classical_points"] == 0


def test_single_reference_runs_decide_the_time_model_too():
    """Against the reference image alone (no template) an STS run makes the same decision
    from its own classical measurement of the sampled frames: on the vibration the points
    are solved classically (measured 144 of 144, every usable row m = 0), on the relaxing
    render none (99.97 % of the rows full windows); the result says so in
    info["time_model"]."""
    mv = synth.synthetic_movie((161, 161), 20, _vibration(161), noise_sigma=2.0, seed=1)
    series = torch.cat([mv.ref[None], mv.frames]).double()
    res = sts.track(series, config=sts.DICConfig(m=2), progress=False, series_reference=False)
    assert "series_reference" not in res.info
    cls = res.info["time_model"]["classical_points"]
    assert cls >= 0.4 * res.n_points, (cls, res.n_points)
    classical = (res.m[1:] == 0) & (res.status[1:] <= 1)
    assert float(classical.double().sum() / (res.status[1:] <= 1).sum()) >= 0.95
    relax = synth.synthetic_movie((161, 161), 20, _relaxing(161), noise_sigma=2.0, seed=3)
    series = torch.cat([relax.ref[None], relax.frames]).double()
    res = sts.track(series, config=sts.DICConfig(m=2), progress=False, series_reference=False)
    assert res.info["time_model"] == {"classical_points": 0, "points": res.n_points}
    assert float((res.m[1:] == 2).double().mean()) > 0.95
    # fewer points than the pooled test's neighbourhood: windows and the model check only
    few = sts.track(series, config=sts.DICConfig(m=2), progress=False, series_reference=False,
                    step=40)
    assert few.n_points < 25 and "time_model" not in few.info


def test_noise_free_movie_keeps_its_windows():
    """On noise-free images a displacement's predicted std is tiny (1.4e-4 px here) and the
    interpolation bias that every solution carries alike (3.7e-4 px RMS classical at 0.3 px
    a frame) bends the windows' line by more: without BIAS_FLOOR_PX every point of this
    linear motion was solved classically (144 of 144, with and without a template)."""
    mv = synth.synthetic_movie((161, 161), 16, synth.Translation(ut=0.3, vt=-0.17),
                               noise_sigma=0.0, seed=4)
    series = torch.cat([mv.ref[None], mv.frames]).double()
    for sr in ("auto", False):
        res = sts.track(series, config=sts.DICConfig(m=2), progress=False, series_reference=sr)
        info = res.info["series_reference" if sr else "time_model"]
        assert info["classical_points"] == 0, (sr, info)
        assert float((res.m[1:] == 2).double().mean()) > 0.95
        assert float((res.ut[1:] - 0.3).abs().nanmedian()) < 2e-3


def test_no_loss_of_accuracy_where_the_time_model_fails_below_the_check():
    """A vibration of 0.03 px (period 4 frames, phase varying over the specimen): the
    windows miss a line by a few standard deviations, which the model check allows, so
    without the pooled bias test they would stay and carry that bias (1.44x and 1.47x
    classical DIC's error, seeds 1 and 2, on the code before it). The pooled test puts
    every point classical here: STS with defaults equals classical DIC (measured 1.000x,
    both seeds)."""
    def weak(x, y, t):
        ph = (x + y) / 15.0
        a = 0.03 * (torch.sin(2 * np.pi * t / 4.0 + ph) - torch.sin(ph))
        return a, -0.5 * a
    mot = synth.Custom(weak)
    mv = synth.synthetic_movie((161, 161), 20, mot, noise_sigma=2.0, seed=1)
    series = torch.cat([mv.ref[None], mv.frames]).double()
    times = torch.cat([torch.zeros(1, dtype=torch.float64), mv.times])
    errs = []
    for m in (0, 2):
        res = sts.track(series, config=sts.DICConfig(m=m), progress=False)
        gt = synth.ground_truth(mot, res.points.double(), times)
        e = torch.stack([res.u.double()[1:] - gt["u"][1:], res.v.double()[1:] - gt["v"][1:]])
        errs.append(float(e[torch.isfinite(e)].pow(2).mean().sqrt()))
    assert errs[1] <= 1.03 * errs[0], errs


def test_one_bad_point_does_not_turn_its_neighbours_classical(monkeypatch):
    """One point whose sampled displacements zig-zag by 6 of its standard deviations (each
    window then misses the line by 4.8, below the model check's limit, so the windows count
    in the pooled bias test): its own excess counts only up to POOL_CLIP times its own gain
    in the pools of its 25 neighbours, and the motion, linear in time, keeps its windows
    everywhere else. On the code before, that one point put itself and 21 neighbours
    classical here; on a 400-frame render of a translation, one point with a wrong peak
    (2.8 px, converged) in its last sampled frames turned 266 of 3,600 points classical."""
    import torch_stsdic.movie.series_reference as sr

    mv = synth.synthetic_movie((161, 161), 20, synth.Translation(ut=0.05, vt=-0.02),
                               noise_sigma=2.0, seed=4)
    series = torch.cat([mv.ref[None], mv.frames]).double()
    measure = sr._measure
    hit = {}

    def measure_with_a_bad_point(plan, frames, image, run, guess=None, ratio=None):
        res = measure(plan, frames, image, run, guess, ratio)
        if image is None:  # the classical measurement the time-model test reads
            k = int(torch.argmin((plan.points.double() - 80.0).norm(dim=1)))
            e = 6.0 * float(res.std["u"][1:, k].median())
            sign = torch.tensor([(-1.0) ** j for j in range(res.u.shape[0])],
                                dtype=res.u.dtype)
            res.u[1:, k] += e * sign[1:]
            hit["point"] = k
        return res

    monkeypatch.setattr(sr, "_measure", measure_with_a_bad_point)
    holds = sts.series_template(series, config=sts.DICConfig(m=2), step=8).model_holds
    assert "point" in hit and holds is not None and holds.numel() > 100
    assert int((~holds).sum()) <= 1, int((~holds).sum())


def test_long_movies_sample_runs_of_adjacent_frames():
    """Over 21 targets, an STS run samples runs of 2m + 3 adjacent frames (three windows each
    for the time-model test), the reference among them; a classical run spreads them."""
    from torch_stsdic.movie.plan import plan_run
    from torch_stsdic.movie.series_reference import sample_frames

    mv = synth.synthetic_movie((61, 61), 40, noise_sigma=1.0, seed=2)
    series = torch.cat([mv.ref[None], mv.frames]).double()
    plan = plan_run(series, config=sts.DICConfig(m=2, subset_size=15), step=10)
    ks = sample_frames(plan, 21)
    assert len(ks) == 21 and ks[0] == 0
    runs = np.split(np.array(ks), np.nonzero(np.diff(ks) > 1)[0] + 1)
    assert [len(r) for r in runs] == [7, 7, 7]
    plan0 = plan_run(series, config=sts.DICConfig(m=0, subset_size=15), step=10)
    k0 = sample_frames(plan0, 21)
    assert len(k0) == 21 and int(np.diff(k0).max()) == 2
    # m = 4: a run is 11 frames, 21 hold one: two, at the movie's start and its end (one
    # alone judged the time model from frames 0-10)
    plan4 = plan_run(series, config=sts.DICConfig(m=4, subset_size=15), step=10)
    k4 = sample_frames(plan4, 21)
    assert k4 == list(range(11)) + list(range(30, 41)), k4
    # where two runs do not fit in the targets: spread one by one
    short = plan_run(series[:26], config=sts.DICConfig(m=6, subset_size=15), step=10)
    k6 = sample_frames(short, 21)
    assert len(k6) == 21 and k6[0] == 0 and k6[-1] == 25, k6


def test_a_fixed_long_window_is_not_judged_from_the_movies_start_alone():
    """A relaxing stretch: fast at the start, then nearly affine in time. With m = 4 the
    time model is judged from runs at the movie's start and its end, so no point is made
    classical for the whole run because the first 11 frames curve (one run at the start
    turned 34 of the 64 points classical)."""
    def fn(x, y, t):
        e = 0.004 * (1 - torch.exp(-t / 8.0))
        return (e * (x - 60) + 0.03 * t + 0.2 * (1 - torch.exp(-t / 5.0)),
                -0.3 * e * (y - 60) - 0.02 * t)

    mv = synth.synthetic_movie((121, 121), 30, synth.Custom(fn), noise_sigma=2.0, seed=1)
    series = torch.cat([mv.ref[None], mv.frames]).double()
    res = sts.track(series, config=sts.DICConfig(m=4, subset_size=21), step=10,
                    progress=False)
    frames = res.info["series_reference"]["frames"]
    assert frames[0] == 0 and frames[-1] == 30 and len(frames) == 22, frames
    m = res.field("m")[1:]
    assert int((m == 0).all(0).sum()) == 0, int((m == 0).all(0).sum())
    assert float((m == 0).double().mean()) < 0.01


def test_splat_with_and_without_the_image_border_mask_agree():
    """Windows wholly inside the image skip the border mask (_splat's fast path); a chunk
    with one window over the border takes the masked path for all its windows. Both must
    give the same sums at the inner windows' pixels."""
    from torch_stsdic.core.interpolation import BSplineImage

    size, half = 96, 7
    img = synth.render(synth.make_speckle((size, size), seed=3), (size, size)).double()
    frame = BSplineImage(img, order=3)
    ref = img.reshape(-1)
    pts = torch.tensor([[30.0, 30.0], [50.3, 41.7], [66.0, 60.0], [3.0, 40.0]],
                       dtype=torch.float64)
    warp = torch.zeros(4, 12, dtype=torch.float64)
    warp[:, 0], warp[:, 1], warp[:, 6], warp[:, 8] = 0.3, 0.01, -0.2, -0.02

    def splat(ok):
        acc = torch.zeros(3, size * size, dtype=torch.float64)
        one = torch.ones(1, dtype=torch.float64)
        template_image.splat(acc, frame, torch.tensor([0]), ref, pts, warp[None],
                                ok[None], half, one, one)
        return acc

    inner = splat(torch.tensor([True, True, True, False]))  # no border: fast path
    border = splat(torch.tensor([False, False, False, True]))
    both = splat(torch.tensor([True, True, True, True]))  # one chunk, masked path
    assert float(inner[1].sum()) > 0 and float(border[1].sum()) > 0
    torch.testing.assert_close(both, inner + border, rtol=1e-12, atol=1e-9)
    # the border window lost its columns left of the image: fewer weights than an inner one
    assert float(border[1].sum()) < 0.9 * float(inner[1].sum()) / 3  # 54 against 64


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_native_splat_equals_the_torch_splat(dtype, monkeypatch):
    """The template's samples in one C++ pass (``native.ops.splat_fused``: map, sample, grey
    levels matched, weights, added) give the torch code's sums, for windows inside the image, over
    its border and mapped partly out of it, in frames of a stack, float32 and float64
    coefficients; quintic too."""
    from torch_stsdic.core.interpolation import BSplineImage
    from torch_stsdic.kernels import dispatch
    from torch_stsdic.kernels.native import loader

    if not loader.usable(torch.zeros(1)):
        pytest.skip("no native kernels (no C++ compiler)")
    size, half = 90, 7
    imgs = torch.stack([synth.render(synth.make_speckle((size, size), seed=s),
                                     (size, size)).double() for s in (8, 9)])
    ref = imgs[0].reshape(-1)
    g = torch.Generator().manual_seed(2)
    pts = torch.rand(40, 2, generator=g, dtype=torch.float64) * (size + 6) - 3  # some outside
    warp = (torch.rand(2, 40, 12, generator=g, dtype=torch.float64) - 0.5) * 0.02
    warp[..., 0] += torch.tensor([0.4, -2.3], dtype=torch.float64)[:, None]
    warp[..., 6] += torch.tensor([-0.7, 1.6], dtype=torch.float64)[:, None]
    ok = torch.rand(2, 40, generator=g) > 0.1
    weight = torch.tensor([1.0, 0.6], dtype=torch.float64)
    level = torch.tensor([1.0, 1.2], dtype=torch.float64)
    planes = torch.tensor([1, 0])
    calls = []
    orig = template_image.native_ops.splat_fused

    def counted(*a, **k):
        calls.append(1)
        return orig(*a, **k)

    for order in (3, 5):
        stack = BSplineImage(imgs.to(dtype), order=order)
        sums = {}
        for path in ("native", "torch"):
            monkeypatch.setattr(template_image.native_ops, "splat_fused", counted)
            if path == "torch":
                monkeypatch.setattr(dispatch, "splat", lambda *a: dispatch.TORCH)
            acc = torch.zeros(3, size * size, dtype=torch.float64)
            n_calls = len(calls)
            template_image.splat(acc, stack, planes, ref, pts, warp, ok, half, weight, level)
            assert (len(calls) > n_calls) == (path == "native")
            sums[path] = acc
            monkeypatch.undo()
        assert float(sums["torch"][1].sum()) > 0
        tol = 1e-9 if dtype == torch.float64 else 2e-4
        torch.testing.assert_close(sums["native"], sums["torch"], rtol=tol, atol=tol)


def test_splat_of_frames_at_once_equals_the_sum_of_each_frame_alone():
    """_splat takes a group of frames (planes of one stack) in one batch: its sums equal
    those of each frame splatted alone and added, the noise share included (a product of
    each frame's own per-pixel sums: summing the frames' weights first would differ)."""
    from torch_stsdic.core.interpolation import BSplineImage

    size, half = 80, 6
    imgs = torch.stack([synth.render(synth.make_speckle((size, size), seed=s),
                                     (size, size)).double() for s in (4, 5, 6)])
    stack = BSplineImage(imgs, order=3)
    ref = imgs[0].reshape(-1)
    g = torch.Generator().manual_seed(1)
    pts = torch.rand(30, 2, generator=g, dtype=torch.float64) * (size - 20) + 10
    warp = (torch.rand(3, 30, 12, generator=g, dtype=torch.float64) - 0.5) * 0.02
    warp[..., 0] += torch.tensor([0.3, -0.4, 1.2], dtype=torch.float64)[:, None]
    ok = torch.rand(3, 30, generator=g) > 0.2
    weight = torch.tensor([1.0, 0.5, 2.0], dtype=torch.float64)
    level = torch.tensor([1.0, 1.3, 0.8], dtype=torch.float64)
    planes = torch.tensor([2, 0, 1])  # frame j in plane planes[j]
    together = torch.zeros(3, size * size, dtype=torch.float64)
    template_image.splat(together, stack, planes, ref, pts, warp, ok, half, weight, level)
    alone = torch.zeros_like(together)
    for j in range(3):  # each frame its own single-frame image
        own = BSplineImage(imgs[int(planes[j])], order=3)
        template_image.splat(alone, own, torch.tensor([0]), ref, pts, warp[j:j + 1],
                                ok[j:j + 1], half, weight[j:j + 1], level[j:j + 1])
    assert float(together[2].sum()) > 0
    torch.testing.assert_close(together, alone, rtol=1e-12, atol=1e-12)
    # the share is per frame: the frames' weights summed before the product would differ
    assert not torch.allclose(together[2], together[1] ** 2 / weight.sum(), rtol=1e-3)


def test_a_later_round_starts_every_row_from_the_earlier_rounds_solution(movie, monkeypatch):
    """The template's second round measures the same frames again (against the first
    round's template): every block starts from the first round's solutions, not from the
    carry moved on over the sampled frames' gaps (on the hourglass that carry landed on a
    wrong peak at ZNCC 0.81 for 63 points, which entered the template)."""
    rounds = []
    orig = series_reference._measure

    def recording(plan, frames, image, run, guess=None, ratio=None):
        res = orig(plan, frames, image, run, guess, ratio)
        rounds.append((guess is not None, len(frames), res))
        return res

    monkeypatch.setattr(series_reference, "_measure", recording)
    _run(movie, 0)
    later = [(n, r) for guessed, n, r in rounds if guessed and n > 1]
    first = [r for guessed, n, r in rounds if not guessed and n > 1]
    assert later and first
    n, res = later[0]
    rows = n * res.n_points
    assert res.info["first_guess_rows"] >= 0.95 * rows  # not only the first block's
    assert float(res.iterations.double().mean()) < float(first[0].iterations.double().mean())


def test_a_later_rounds_blocks_are_as_long_as_the_budget_allows(movie, monkeypatch):
    """Every block of a later round starts from the earlier round's solutions, so none
    extrapolates a carry: its first target is not alone and a block holds as many targets as
    the memory budget allows (the CPU's cap of 8 guards the carry). The same rows as in
    the first round's blocks, to the solver's tolerance."""
    from torch_stsdic.movie import plan as plan_mod

    blocks, results = [], {}
    orig = series_reference._measure

    def recording(plan, frames, image, run, guess=None, ratio=None):
        def seen(sub, *a, **kw):
            if guess is not None:
                blocks.append(sub.blocks)
            return run(sub, *a, **kw)
        res = orig(plan, frames, image, seen, guess, ratio)
        if guess is not None and len(frames) > 1:
            results.setdefault(key, []).append(res)
        return res

    monkeypatch.setattr(series_reference, "_measure", recording)
    key = "budget"
    _run(movie, 0)
    assert blocks and all(len(b[0]) > 1 or len(sum(b, [])) == 1 for b in blocks)
    n = len(blocks[0][0])  # the sampled frames, in one block
    assert len(blocks[0]) == 1 and n > plan_mod.MAX_DEFAULT_BATCH + 1
    # the later round in the carried runs' blocks (first alone, then 8): the same rows
    monkeypatch.setattr(series_reference, "guessed_blocks",
                        lambda p: plan_mod.dataclasses.replace(p, batch_frames=8))
    key, blocks[:] = "carried", []
    _run(movie, 0)
    assert [len(b) for b in blocks[0]] == [1, 8, n - 9]
    a, b = results["budget"][0], results["carried"][0]
    assert torch.equal(a.status, b.status)
    for name in ("u", "v"):
        assert torch.allclose(a.field(name), b.field(name), atol=1e-4, rtol=0, equal_nan=True)


def test_the_rounds_against_the_template_take_its_known_noise_ratio(movie, monkeypatch):
    """The template's later rounds and its gauge measure against the template, whose noise
    ratio its own construction gives (``template_image``): their blocks take it, they do
    not estimate it again from the template's and the frames' pixels (Immerkaer over whole
    images: 0.4 s of the hourglass's template)."""
    import torch_stsdic.movie.block as block

    estimated, made, rounds = [], [], []
    orig_ratio, orig_image, orig_measure = (block.noise_ratio, template_image.template_image,
                                            series_reference._measure)

    def ratio(desc, raw, frames):
        estimated.append(desc)
        return orig_ratio(desc, raw, frames)

    def image(*a, **kw):
        out = orig_image(*a, **kw)
        made.append(out[1])
        return out

    def measure(plan, frames, image, run, guess=None, ratio=None):
        res = orig_measure(plan, frames, image, run, guess, ratio)
        rounds.append((image is not None, res.info["reference_noise_ratio"]))
        return res

    monkeypatch.setattr(block, "noise_ratio", ratio)
    monkeypatch.setattr(series_reference, "template_image", image)
    monkeypatch.setattr(series_reference, "_measure", measure)
    _run(movie, 0)
    against = [r for on_template, r in rounds if on_template]
    assert len(against) == 2 and len(made) == 2  # round 2 and the gauge; two templates
    assert against[0] == pytest.approx(made[0]) and against[1] == pytest.approx(made[1])
    assert 0.0 < made[1] < 0.5  # 16 frames and the reference: well below a frame's
    assert not any(str(d).startswith("array:") for d in estimated)


def _fit_grid(n: int = 15, step: float = 10.0) -> torch.Tensor:
    xs = torch.arange(n, dtype=torch.float64) * step
    return torch.stack(torch.meshgrid(xs, xs, indexing="xy"), -1).reshape(-1, 2)


def _warps_of(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """(F, N, 6) warps with the values u, v (F, N) (gradients unused by the choice)."""
    w = torch.zeros(*u.shape, 6, dtype=torch.float64)
    w[..., 0], w[..., 3] = u, v
    return w


def test_the_registration_takes_the_largest_neighbourhood_the_field_allows():
    """The fit that registers a frame at a POI is the passing one of least variance factor:
    on a field linear in space the plane over 81 POIs at the grid's centre (w^T R w 0.049
    at step 10, subset 21, against 0.144 for the plane over 25: the template's registration
    error, which every row carries, a third in variance); on a strongly curved field every
    plane fails and a quadratic registers it, on a field that bends beyond a quadratic over
    5 x 5 POIs a cubic over 25; an untrusted POI keeps the fits that would
    include it out (a smaller neighbourhood is taken around it)."""
    torch.manual_seed(0)
    pts = _fit_grid(19)
    n = len(pts)
    x, y = pts[:, 0] - 20, pts[:, 1] - 20  # the grid's centre at 70, 70
    reg = series_reference.RegistrationFits.make(pts, 25, 21)
    assert [f.index.shape[1] for f in reg.fits] == [25, 49, 81]
    # a grid of 225 POIs: 81 is over a third of them, not local
    assert [f.index.shape[1] for f in series_reference.RegistrationFits.make(
        _fit_grid(15), 25, 21).fits] == [25, 49]
    centre = 9 * 19 + 9
    plane25 = reg.factor[reg.candidates.index((0, 1)), centre]
    plane81 = reg.factor[reg.candidates.index((2, 1)), centre]
    assert abs(float(plane25) - 0.1437) < 2e-3 and abs(float(plane81) - 0.0493) < 2e-3
    unit = torch.full((n,), 1e-4, dtype=torch.float64)  # (0.01 px)^2 one image's share
    noise = 0.01 * torch.randn(4, 2, n, dtype=torch.float64)
    linear = 0.002 * (x - 70) + 0.1
    curved = 2e-4 * (x - 70) ** 2 + 1e-4 * (y - 70) ** 2  # 0.49 px over the grid
    cubic = 5e-5 * (x - 40) ** 3  # bends beyond a quadratic over 5 x 5 POIs
    u = torch.stack([linear, curved, linear, cubic]) + noise[:, 0]
    v = torch.stack([-0.5 * linear, curved, -0.5 * linear, -cubic]) + noise[:, 1]
    ok = torch.ones(4, n, dtype=torch.bool)
    bad = centre + 3  # three columns right of the centre: inside its 7 x 7 block
    ok[2, bad] = False
    choice = series_reference._fit_choice(reg, _warps_of(u, v), ok, unit)
    assert reg.candidates[int(choice[0, centre]) - 1] == (2, 1)  # a plane over 81
    deg = reg.degree(choice)
    assert bool((deg[1][choice[1] > 0] == 2).all())  # curved: only quadratics
    assert float((choice[1] > 0).double().mean()) > 0.5
    # frame 2: the centre's 49 and 81 neighbourhoods hold the untrusted POI: its 25's do not
    assert reg.candidates[int(choice[2, centre]) - 1] == (0, 1)
    assert bool(reg.guard(choice, ok)[2, centre])
    # frame 3: only the cubic over 25 POIs follows it, and its value is the field's
    assert reg.candidates[int(choice[3, centre]) - 1] == (0, 3)
    smooth = series_reference._smooth(reg, _warps_of(u, v), ok, choice)
    assert abs(float(smooth[3, centre, 0] - cubic[centre])) < 0.02  # noise 0.01 per POI
    # the variance factor the template's registration is predicted with follows the choice
    assert abs(float(reg.variance(choice)[0, centre]) - float(plane81)) < 1e-12
    assert float(reg.variance(choice)[2, centre]) == pytest.approx(float(plane25))


def test_equal_factors_keep_the_lower_degree_and_the_maps_are_the_chosen_fits():
    """At a POI whose 25 neighbours lie symmetric about it the cubic's value weights are the
    quadratic's (equal variance factors, to rounding): where both pass, the quadratic (listed
    first) registers the frame, not whichever rounding favours. The maps (_smooth) are each
    chosen fit's value, slopes and second-order terms (LocalFit.apply*) at its frames and
    POIs, the POI's own warp elsewhere."""
    pts = _fit_grid(15)  # fits over 25 and 49 POIs
    n = len(pts)
    reg = series_reference.RegistrationFits.make(pts, 25, 21)
    centre = 7 * 15 + 7
    quad, cubic = reg.candidates.index((0, 2)), reg.candidates.index((0, 3))
    fq, fc = float(reg.factor[quad, centre]), float(reg.factor[cubic, centre])
    assert fq == pytest.approx(fc, rel=1e-12)
    torch.manual_seed(1)
    x, y = pts[:, 0] - 70, pts[:, 1] - 70
    curved = 2e-4 * x ** 2 + 1e-4 * y ** 2  # every plane fails, the quadratic passes
    u = curved[None] + 0.01 * torch.randn(2, n, dtype=torch.float64)
    v = -curved[None] + 0.01 * torch.randn(2, n, dtype=torch.float64)
    ok = torch.ones(2, n, dtype=torch.bool)
    ok[:, centre + 3] = False  # in the centre's 49 neighbours, not its 25
    unit = torch.full((n,), 1e-4, dtype=torch.float64)
    warps = _warps_of(u, v)
    warps[..., 1] = 0.3  # a gradient of its own: kept where no fit is chosen
    choice = series_reference._fit_choice(reg, warps, ok, unit)
    assert int(choice[0, centre]) == quad + 1 and int(choice[1, centre]) == quad + 1
    reg.factor[cubic, centre] = fq * (1 - 1e-13)  # rounding's side: still the quadratic
    assert int(series_reference._fit_choice(reg, warps, ok, unit)[0, centre]) == quad + 1
    reg.factor[cubic, centre] = fq * (1 - 1e-6)  # a real difference: the cubic
    assert int(series_reference._fit_choice(reg, warps, ok, unit)[0, centre]) == cubic + 1
    choice[1, :50] = 0  # no fit: the POI's own warp
    choice[1, 50:60] = cubic + 1
    ok[:, centre + 3] = True
    out = series_reference._smooth(reg, warps, ok, choice)
    # the fits with every weight kept (the registration keeps few; _smooth makes them)
    full = [local_fit_weights(pts, f.index.shape[1], 21, degrees=(1, 2, 3)) for f in reg.fits]
    for c, o in ((0, 0), (3, 6)):
        for k, (i, d) in enumerate(reg.candidates):
            fit, here = full[i], choice == k + 1
            want = torch.cat([fit.apply(d, warps[..., c])[..., None],
                              fit.apply_slopes(d, warps[..., c]),
                              fit.apply_quadratic(d, warps[..., c])], -1)
            torch.testing.assert_close(out[..., o:o + 6][here], want[here])
    torch.testing.assert_close(out[1, :50, 0:3], warps[1, :50, 0:3])
    assert bool((out[1, :50, 3:6] == 0).all())


def _kept_bytes(reg: series_reference.RegistrationFits) -> int:
    """Bytes of the tensors a RegistrationFits keeps (its fits' and its factors)."""
    total = 0 if reg._factor is None else reg._factor.nbytes
    for fit in reg.fits:
        total += fit.index.nbytes + fit.offsets.nbytes + fit.used.nbytes
        for kept in (fit.weights, fit.slopes, fit.quadratic, fit.posed):
            total += sum(t.nbytes for t in kept.values())
    return total


def test_the_registration_fits_keep_a_few_kb_a_poi_and_the_maps_work_by_chunks(monkeypatch):
    """What the registration keeps grows with N by a small constant: the neighbours' index,
    offsets and use over 25, 49 and 81 POIs (155 x 32 bytes a POI), whether each fit is
    posed, the factors and the smallest neighbourhood's planes (the gauge's) -- 6.2 kB a POI
    today, under 8 kB; keeping every degree's weights (round 5) took 28.5 kB a POI (250k POIs:
    7 GB). The maps (_smooth) make the chosen fits' weights by chunks of POIs: the same
    maps with chunks of one POI as with the default's."""
    sizes = {}
    for side in (30, 45):  # 900 and 2,025 POIs: fits over 25, 49, 81
        reg = series_reference.RegistrationFits.make(_fit_grid(side), 25, 21)
        assert [f.index.shape[1] for f in reg.fits] == [25, 49, 81]
        _ = reg.factor
        sizes[side * side] = _kept_bytes(reg)
    for n, b in sizes.items():
        assert b / n < 8000, (n, b / n)
    (n0, b0), (n1, b1) = sizes.items()
    assert abs(b1 / n1 - b0 / n0) < 0.02 * b0 / n0  # linear in N
    torch.manual_seed(2)
    pts = _fit_grid(30)
    n = len(pts)
    reg = series_reference.RegistrationFits.make(pts, 25, 21)
    x = pts[:, 0] - 150
    u = (1e-4 * x ** 2)[None] + 0.01 * torch.randn(3, n, dtype=torch.float64)
    v = (-0.002 * x)[None] + 0.01 * torch.randn(3, n, dtype=torch.float64)
    warps, ok = _warps_of(u, v), torch.ones(3, n, dtype=torch.bool)
    choice = series_reference._fit_choice(reg, warps, ok, torch.full((n,), 1e-4,
                                                                      dtype=torch.float64))
    assert len(set(choice.unique().tolist())) >= 3  # several candidates chosen
    out = series_reference._smooth(reg, warps, ok, choice)
    monkeypatch.setattr(series_reference, "MAP_CHUNK", 1)
    torch.testing.assert_close(series_reference._smooth(reg, warps, ok, choice), out,
                               rtol=0, atol=1e-13)


def test_the_larger_neighbourhoods_lower_the_templates_registration_error(monkeypatch):
    """The error every row shares is the reference image's noise seen through the fits that
    registered the frames: with only the reference frame noisy (the other frames nearly
    noise-free), classical DIC against the template errs by each point's registration
    error. Fits over 25 .. 81 POIs (the default) against fits over 25 only: measured 0.70x
    (2.18e-3 / 3.10e-3 px RMS over the frames and points; variance factors 0.049 / 0.144 at
    the grid's centre, more at its edges); band 0.8."""
    mot = synth.Custom(lambda x, y, t: (0.05 * t + 0.0004 * t * (x - 100), -0.03 * t))
    mv = synth.synthetic_movie((201, 201), 10, mot, noise_sigma=0.0, seed=3)
    clean = torch.cat([mv.ref[None], mv.frames]).double()
    times = torch.cat([torch.zeros(1, dtype=torch.float64), mv.times])
    gen = torch.Generator().manual_seed(5)
    scale = torch.full((len(clean), 1, 1), 0.05, dtype=torch.float64)
    scale[0] = 2.0
    series = clean + torch.randn(clean.shape, generator=gen, dtype=torch.float64) * scale

    def err():
        res = sts.track(series, config=sts.DICConfig(m=0, subset_size=21), step=8,
                        progress=False, series_reference=True)
        gt = synth.ground_truth(mot, res.points.double(), times)
        e = torch.stack([res.u.double()[1:] - gt["u"][1:], res.v.double()[1:] - gt["v"][1:]])
        return float(e[torch.isfinite(e)].pow(2).mean().sqrt())
    ladder = err()
    monkeypatch.setattr(series_reference, "NEIGHBOURHOODS", (25,))
    small = err()
    assert ladder <= 0.8 * small, (ladder, small)


def test_splat_over_the_covered_pixels_equals_the_splat_into_the_image():
    """template_image adds every frame's sums over the pixels the windows cover and maps
    them to the image once (``acc`` (3, C)); splat into the whole image (``acc`` (3, H*W))
    gives the same sums at those pixels and nothing elsewhere, border windows included."""
    from torch_stsdic.core.interpolation import BSplineImage

    size, half = 72, 5
    imgs = torch.stack([synth.render(synth.make_speckle((size, size), seed=s),
                                     (size, size)).double() for s in (7, 8)])
    stack = BSplineImage(imgs, order=3)
    ref = imgs[0].reshape(-1)
    g = torch.Generator().manual_seed(2)
    pts = torch.rand(20, 2, generator=g, dtype=torch.float64) * (size - 10) + 5
    pts[0] = torch.tensor([2.0, 30.0], dtype=torch.float64)  # a window over the border
    warp = (torch.rand(2, 20, 12, generator=g, dtype=torch.float64) - 0.5) * 0.02
    warp[..., 0] += 0.4
    ok = torch.ones(2, 20, dtype=torch.bool)
    weight = torch.tensor([1.0, 0.7], dtype=torch.float64)
    level = torch.tensor([1.0, 1.1], dtype=torch.float64)
    planes = torch.tensor([0, 1])
    cover = template_image.window_pixels(pts, half, size, size)
    image = torch.zeros(3, size * size, dtype=torch.float64)
    on_cover = torch.zeros(3, cover[0].numel(), dtype=torch.float64)
    for j in range(2):  # frame by frame, as template_image on the CPU
        for acc in (image, on_cover):
            template_image.splat(acc, stack, planes[j:j + 1], ref, pts, warp[j:j + 1],
                                 ok[j:j + 1], half, weight[j:j + 1], level[j:j + 1], cover)
    mapped = torch.zeros_like(image)
    mapped[:, cover[0]] = on_cover
    assert float(on_cover[1].sum()) > 0 and float(on_cover[2].sum()) > 0
    torch.testing.assert_close(mapped, image, rtol=1e-12, atol=1e-9)


def test_the_carry_starts_the_next_block_where_the_solves_measure(movie, monkeypatch):
    """Stored rows have the template's gauge subtracted (the reference frame's measurement
    of the template's registration); the solves measure against the template itself. The
    next block's carried guess is the last solved row in the solves' own terms (the stored
    row with the gauge added back), not the stored row: started from that, every carried
    row began the gauge away from its solution (0.01 px a point on the hourglass)."""
    import torch_stsdic.movie.series as series_mod

    solved, seeds = {}, {}
    orig_solve, orig_carry = series_mod.solve_block, series_mod.make_carry

    def solve(run, ks, ref, carry):
        out = orig_solve(run, ks, ref, carry)
        if run.m > 0 and ref.frame == -1:  # the main run's blocks, against the template
            solved[tuple(ks)] = {nm: out[nm][-1].double().cpu() for nm in ("u", "v", "uy")}
        return out

    def carry(rows, times, names, prev, dtype, device, frames=None):
        out = orig_carry(rows, times, names, prev, dtype, device, frames=frames)
        if "ut" in names:
            seeds[tuple(frames)] = out
        return out

    monkeypatch.setattr(series_mod, "solve_block", solve)
    monkeypatch.setattr(series_mod, "make_carry", carry)
    res = _run(movie, 2, batch_frames=4)
    assert res.info["series_reference"]["gauge_rms_px"] > 1e-4  # measurable here
    # the reference frame's row is stored as the truth (0), not as solved: not compared
    blocks = [ks for ks in solved if ks in seeds and 0 not in ks]
    assert len(blocks) >= 3
    for ks in blocks:
        for nm in ("u", "v", "uy"):
            got, want = seeds[ks].vals[nm].double(), solved[ks][nm]
            ok = torch.isfinite(got) & torch.isfinite(want)
            # the carry holds the stored (float32) row: the solved one within its rounding
            torch.testing.assert_close(got[ok], want[ok], rtol=0, atol=2e-6)
