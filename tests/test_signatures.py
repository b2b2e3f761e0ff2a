"""Thin wrappers show (and enforce) the parameters of the functions they wrap."""

import inspect

import pytest

from torch_stsdic import plot
from torch_stsdic.core import noise
from torch_stsdic.core.signatures import bind, param, signature_like
from torch_stsdic.movie import distributed, series

P, K = inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY


def _params(fn):
    return [(p.name, p.default, p.kind) for p in inspect.signature(fn).parameters.values()]


def test_track_keeps_its_public_signature():
    """track is written out (the entry point a user reads); this pins its parameters."""
    e = inspect.Parameter.empty
    assert _params(series.track) == [
        ("series", e, P), ("reference", 0, P), ("frames", None, P), ("points", None, P),
        ("roi", None, P), ("mask", None, P), ("step", 10, P), ("config", None, P),
        ("device", "cpu", P), ("times", None, P), ("progress", True, P), ("out", None, P),
        ("resume", False, P), ("batch_frames", None, P), ("reference_update", None, P),
        ("smoothing", None, P), ("lost_zncc", 0.8, K), ("checks", True, K),
        ("overwrite", False, K), ("callback", None, K), ("refine_reference", False, K),
        ("series_reference", "auto", K), ("series_frames", None, K),
        ("refine_frames", None, K), ("shared_motion", "auto", K), ("find_specimen", True, K),
        ("strain_window", 5, K), ("strain_kind", "green", K), ("scale", None, K),
        ("unit", None, K), ("time_unit", None, K), ("run_estimates", None, K),
        ("window_length", "fixed", K)]
    with pytest.raises(TypeError):
        series.track("x", nonsense=1)
    with pytest.raises(ValueError, match="resume: needs out"):
        series.track("x", resume=True)


def test_wrappers_show_the_wrapped_parameters():
    assert _params(noise.predicted_std) == _params(noise.predicted_covariance)
    d = _params(distributed.track_distributed)
    assert [n for n, _, _ in d] == [
        "series", "chunk_frames", "client", "n_workers", "threads_per_worker", "processes",
        "torch_threads", "out", "resume", "overwrite", "progress", "callback", "track_kwargs"]
    hist = inspect.signature(plot.plot_history).parameters
    assert hist["xlabel"].default == "time (frame)" and "marker" not in hist
    err = inspect.signature(plot.plot_error_vs_noise).parameters
    assert list(err)[:2] == ["sigmas", "errors"] and err["ylabel"].default == "RMS error (px)"
    with pytest.raises(TypeError):
        plot.plot_history([0, 1], {"a": [0, 1]}, marker="o")  # not a parameter of the preset


def test_signature_like_edits():
    def f(a, b=1, *, c=2, d=3):
        return a

    sig = signature_like(f, insert={"c": [param("x", 0)]}, replace={"a": param("z", kind=P)},
                         drop=["d"], positional=["c"], defaults={"b": 5})
    assert [(p.name, p.default, p.kind) for p in sig.parameters.values()] == [
        ("z", inspect.Parameter.empty, P), ("b", 5, P), ("c", 2, P), ("x", 0, K)]
    assert bind(sig, 1, c=4) == {"z": 1, "b": 5, "c": 4, "x": 0}
    with pytest.raises(TypeError):
        bind(sig, 1, d=2)
