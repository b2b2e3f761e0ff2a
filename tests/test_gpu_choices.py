"""A run with a GPU's choices (``torch_stsdic.movie.choices``: masked solves of a block's
groups of rows, every shorter window at once, every ring of the neighbour fill), taken on
the CPU: the same result file as with the CPU's choices, to the bit."""

from __future__ import annotations

import pytest

from torch_stsdic.kernels import native


def _run(tmp_path, name: str, movie, args=()) -> dict:
    import h5py

    from torch_stsdic.cli import main

    path = tmp_path / f"{name}.h5"
    assert main(["run", str(movie), "--subset", "21", "--step", "10", "--threads", "1",
                 "--no-progress", "--out", str(path), *args]) == 0
    with h5py.File(path) as f:
        return {k: f[k][()] for k in f if isinstance(f[k], h5py.Dataset)}


@pytest.mark.parametrize("args", [(), ("--m", "3")], ids=["chosen-windows", "m3"])
def test_a_gpu_runs_choices_give_the_cpu_runs_file(tmp_path, monkeypatch, args):
    """A speckle moving right by 1.5 px a frame out of a 160 px view: near the border the
    blocks move subsets inside, shorten windows and leave rows OUTSIDE (``keep_outside``),
    rescue rows, solve groups of half-widths. With a GPU's choices the groups are masked
    solves over all the rows (``SubsetSolver.solve(active=)``), with the CPU's each group
    alone; the files are the same to the bit."""
    from torch_stsdic.cli import main
    from torch_stsdic.core.solver import SubsetSolver
    from torch_stsdic.movie import choices

    if not native.available():
        pytest.skip("no native kernels (the two paths agree to the bit on the C++ kernels)")
    assert main(["synth", "--out", str(tmp_path / "m"), "--size", "160", "--frames", "24",
                 "--motion", "translation", "--ut", "1.5", "--vt", "0.2", "--noise", "2",
                 "--seed", "4", "--threads", "1"]) == 0
    movie = tmp_path / "m" / "movie.tif"
    solve = SubsetSolver.solve
    masked = []

    def spy(self, *a, active=None, **k):
        if active is not None:
            masked.append(int(active.numel()))
        return solve(self, *a, active=active, **k)

    monkeypatch.setattr(SubsetSolver, "solve", spy)
    out = {}
    for gpu in (False, True):
        for name, value in choices.gpu_choices().items():
            monkeypatch.setattr(choices, name, value if gpu else not value)
        masked.clear()
        out[gpu] = _run(tmp_path, f"g{int(gpu)}", movie, args)
        if gpu:
            assert len(masked) >= 2, masked  # the groups solved masked
        else:
            assert not masked
    st, m = out[True]["status"], out[True]["m"]
    assert (st == 3).sum() > 50  # OUTSIDE: the points that left the view
    assert ((m > 0) & (m < m.max())).sum() > 20  # windows shortened
    assert out[True].keys() == out[False].keys()
    for k, v in out[True].items():
        assert v.tobytes() == out[False][k].tobytes(), k
