"""Mutation check: deliberate breakages of the product, each of which the default test suite
must catch (issue 39).

Every mutation is one text substitution in one file of ``torch_stsdic/``. For each, the
repository is copied to a temporary folder (without ``.git``), the substitution applied (it
must match exactly once), and the test files that exercise that area run there with the
default options (``-m 'not slow'``) and ``-x -q``. The mutation is *caught* when pytest
fails; it *survives* when the tests pass. A substitution that no longer matches the source
(the code moved on) is reported as *stale*: update the list.

    python scripts/tools/mutation_check.py              # every mutation, a table, exit 1 if any
                                                        # survives or is stale
    python scripts/tools/mutation_check.py --list       # the mutations
    python scripts/tools/mutation_check.py --only criterion-ssd-as-znssd cli-drops-shape

Results are recorded in docs/testing.md. tests/test_mutation_check.py (slow) runs it.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


@dataclass(frozen=True)
class Mutation:
    name: str
    area: str
    path: str  # relative to the repository root
    old: str
    new: str
    tests: tuple[str, ...]  # test files (relative to tests/) that must catch it
    what: str


OPTIONS = "test_options.py"
STRAIN = "test_strain_end_to_end.py"
HEADLINE = "test_headline_numbers.py"

MUTATIONS: tuple[Mutation, ...] = (
    Mutation(
        "solver-default-tol-1000x", "solver", "torch_stsdic/core/config.py",
        "    tol: float = 1e-4\n", "    tol: float = 1e-1\n",
        (OPTIONS, HEADLINE, "test_solver.py"),
        "Gauss-Newton stops 1000x too early by default (DICConfig.tol 0.1 px)"),
    Mutation(
        "solver-drops-time-terms", "solver", "torch_stsdic/core/solver.py",
        "return self.shape if has_time else self.shape.spatial()",
        "return self.shape.spatial()",
        (HEADLINE, OPTIONS, "test_solver.py"),
        "STS-DIC windows solved without the temporal terms (no velocity, frames not "
        "joined in time)"),
    Mutation(
        "criterion-ssd-as-znssd", "criteria", "torch_stsdic/core/formulations/base.py",
        'znssd=criterion == "znssd"', "znssd=True",
        (OPTIONS, "test_solver.py"),
        'criterion="ssd" runs as ZNSSD'),
    Mutation(
        "criterion-znssd-as-ssd", "criteria", "torch_stsdic/core/formulations/base.py",
        'znssd=criterion == "znssd"', "znssd=False",
        (OPTIONS, "test_solver.py"),
        'criterion="znssd" runs as SSD'),
    Mutation(
        "quintic-as-cubic", "interpolation", "torch_stsdic/core/config.py",
        'return 3 if self.interpolation == "cubic" else 5', "return 3",
        (OPTIONS, "test_interpolation.py"),
        'interpolation="quintic" runs as cubic'),
    Mutation(
        "quadratic-shape-as-affine", "shape", "torch_stsdic/core/shape.py",
        '_SHAPES = {"affine": AffineShape, "quadratic": QuadraticShape}',
        '_SHAPES = {"affine": AffineShape, "quadratic": AffineShape}',
        (OPTIONS, "test_shape.py"),
        'shape="quadratic" runs as affine'),
    Mutation(
        "gaussian-window-as-square", "window", "torch_stsdic/core/window.py",
        '"gaussian": GaussianWindow}', '"gaussian": SquareWindow}',
        (OPTIONS,),
        'window="gaussian" runs as square'),
    Mutation(
        "circular-window-as-square", "window", "torch_stsdic/core/window.py",
        '"circular": CircularWindow,', '"circular": SquareWindow,',
        (OPTIONS,),
        'window="circular" runs as square'),
    Mutation(
        "green-strain-as-small", "strain", "torch_stsdic/analysis/strain.py",
        '    if kind == "small":\n        out["exx"]', '    if True:\n        out["exx"]',
        (STRAIN, OPTIONS),
        "Green-Lagrange strains computed as small strains"),
    Mutation(
        "strain-u-v-swapped", "strain", "torch_stsdic/analysis/result.py",
        "self.points, self.u, self.v, window=window", "self.points, self.v, self.u, window=window",
        (STRAIN, OPTIONS),
        "TrackResult.strain (and so every run's strains) with u and v swapped"),
    Mutation(
        "strain-rate-ut-vt-swapped", "strain", "torch_stsdic/analysis/result.py",
        "ut=self.ut if has_rate else None, vt=self.vt if has_rate else None",
        "ut=self.vt if has_rate else None, vt=self.ut if has_rate else None",
        (STRAIN, OPTIONS),
        "strain rates of a run from ut and vt swapped"),
    Mutation(
        "strain-window-ignored", "strain", "torch_stsdic/movie/sinks.py",
        "window=self.strain_window, kind=self.strain_kind,",
        "window=5, kind=self.strain_kind,",
        (OPTIONS, STRAIN),
        "the result file's strains always over 5x5 points (strain_window ignored)"),
    Mutation(
        "averaged-reference-is-first-frame", "reference", "torch_stsdic/movie/plan.py",
        "raw = series.mean_of(idx, dtype=torch.float64)",
        "raw = series.mean_of(idx[:1], dtype=torch.float64)",
        (OPTIONS, "test_series.py"),
        'reference="0:5" uses frame 0 alone'),
    Mutation(
        "reference-never-updated", "reference", "torch_stsdic/movie/reference.py",
        "if frame == ref.frame or z.size == 0 or not float(z.mean()) < thr:",
        "if True:",
        (OPTIONS, "test_series.py"),
        "reference_update never takes a new reference"),
    Mutation(
        "refined-offsets-not-subtracted", "reference", "torch_stsdic/movie/refine.py",
        "out = _shifted(rows, offsets, -1.0)", "out = dict(rows)",
        (OPTIONS, "test_refine.py", "test_demo.py"),
        "refine_reference measures the offsets but does not subtract them"),
    Mutation(
        "mask-ignored", "points", "torch_stsdic/analysis/points.py",
        "pts = pts[m[pts[:, 1].long(), pts[:, 0].long()]]", "pts = pts",
        (OPTIONS, "test_series.py"),
        "the grid keeps points on zero mask pixels"),
    Mutation(
        "cli-drops-criterion", "CLI", "torch_stsdic/cli/run.py",
        "criterion=args.criterion,", 'criterion="znssd",',
        (OPTIONS, "test_cli.py"),
        "stsdic run ignores --criterion"),
    Mutation(
        "cli-drops-shape", "CLI", "torch_stsdic/cli/run.py",
        "shape=args.shape,", 'shape="affine",',
        (OPTIONS, "test_cli.py"),
        "stsdic run ignores --shape"),
    Mutation(
        "cli-drops-window", "CLI", "torch_stsdic/cli/run.py",
        "window=args.window,", 'window="square",',
        (OPTIONS, "test_cli.py"),
        "stsdic run ignores --window"),
    Mutation(
        "cli-drops-interpolation", "CLI", "torch_stsdic/cli/run.py",
        "interpolation=args.interpolation,", 'interpolation="cubic",',
        (OPTIONS, "test_cli.py"),
        "stsdic run ignores --interpolation"),
    Mutation(
        "cli-drops-strain-kind", "CLI", "torch_stsdic/cli/run.py",
        "strain_kind=args.strain_kind)", 'strain_kind="green")',
        (OPTIONS, STRAIN, "test_cli.py"),
        "stsdic run ignores --strain-kind"),
    Mutation(
        "cli-drops-reference-update", "CLI", "torch_stsdic/cli/run.py",
        "reference_update=args.reference_update,", "reference_update=None,",
        (OPTIONS, "test_cli.py"),
        "stsdic run ignores --reference-update"),
    Mutation(
        "cli-averaged-reference-is-first-frame", "CLI", "torch_stsdic/cli/run.py",
        '"reference": refs[0] if len(refs) == 1 else args.reference,',
        '"reference": refs[0],',
        (OPTIONS, "test_cli.py"),
        "stsdic run --reference 0:5 uses frame 0 alone"),
    Mutation(
        "export-units-ignored", "exports", "torch_stsdic/io/units.py",
        "return 1.0 if d is None else self.length_factor ** d[0]", "return 1.0",
        ("test_export.py",),
        "exports (CSV, VTK, MAT) in px although the file records a scale"),
    Mutation(
        "resume-replays-wrong-rows", "resume", "torch_stsdic/io/results.py",
        "return {nm: f[nm][first : last + 1] for nm in (fields or self.fields)}",
        "return {nm: f[nm][0 : last + 1 - first] for nm in (fields or self.fields)}",
        ("test_series.py", "test_io.py", "test_faults.py"),
        "a resumed run replays the file's first rows instead of the finished block's"),
    Mutation(
        "time-model-bias-ignored", "reference", "torch_stsdic/movie/series_reference.py",
        "biased = excess[nb].sum(1) > gain[nb].sum(1)",
        "biased = torch.zeros_like(gain, dtype=torch.bool)",
        ("test_series_reference.py",),
        "windows that pass the model check with a bias are kept where the time model fails"),
    Mutation(
        "classical-points-solved-by-windows", "reference", "torch_stsdic/movie/block.py",
        "cap = torch.where(cls, 0, run.m if cap is None else cap).to(torch.int8)",
        "cap = torch.where(cls & False, 0, run.m if cap is None else cap).to(torch.int8)",
        ("test_series_reference.py",),
        "rows at points decided classical take the window a rescue or FFT start gives them"),
    Mutation(
        "jump-test-reaches-one-pair-too-far", "shared motion",
        "torch_stsdic/core/shared_motion.py",
        "torch.arange(1, reach + 1, device=dev)])",
        "torch.arange(1, reach + 2, device=dev)])",
        ("test_host_reads.py",),
        "the shared-motion pass's jump test compares a pair with the pairs one beyond its "
        "reach on one side"),
    Mutation(
        "shared-median-bisects-too-few-steps", "shared motion",
        "torch_stsdic/core/shared_fit.py",
        "    for _ in range(63):\n", "    for _ in range(40):\n",
        ("test_long_movies.py", "test_host_reads.py"),
        "the shared fit's device-side median stops its bisection before the bounds meet"),
    Mutation(
        "gpu-batches-ignore-their-budget", "solver", "torch_stsdic/core/gauss_newton.py",
        "            budget = max(budget, gpu_mb)\n", "            budget = budget\n",
        ("test_series.py",),
        "a GPU solves in batches of memory_mb's 256 MiB, not its own budget"),
    Mutation(
        "gpu-ignores-the-budget-given", "solver", "torch_stsdic/core/gauss_newton.py",
        "        if gpu_mb is not None and self.cfg.gpu_floor:",
        "        if gpu_mb is not None:",
        ("test_series.py",),
        "a GPU takes its own 2 GiB batches where the run was given a smaller memory_mb"),
    Mutation(
        "fft-ignores-the-budget-given", "initial guess", "torch_stsdic/core/solver.py",
        "        floor = cfg.gpu_floor", "        floor = True",
        ("test_threads.py",),
        "the FFT searches take a GPU's 2 GiB where the run was given a smaller memory_mb"),
    Mutation(
        "wrong-guess-not-caught", "block guesses", "torch_stsdic/movie/block_guess.py",
        "        if wrong:\n            raise GuessWrong(wrong, whole)\n",
        "        if wrong and False:\n            raise GuessWrong(wrong, whole)\n",
        ("test_block_guess.py",),
        "a block keeps a guessed answer \"nothing to do\" that its numbers contradict"),
    Mutation(
        "compacted-rows-over-capacity-kept", "block guesses",
        "torch_stsdic/movie/block_guess.py",
        "                holds = d.limit < 0 or part[0] <= d.limit\n",
        "                holds = True\n",
        ("test_block_guess.py",),
        "a masked solve taken to C rows where more were asked for leaves the rest unsolved"),
    Mutation(
        "compacted-padding-on-a-solved-row", "block guesses", "torch_stsdic/core/solver.py",
        "                    dest = torch.where(dest >= 0, dest, n)",
        "                    dest = dest.clamp(min=0)",
        ("test_masked_solve.py",),
        "a solve to a capacity puts its padding rows' results on its first row (a solved one)"),
    Mutation(
        "reading-block-takes-fewer-than-its-count", "block guesses",
        "torch_stsdic/movie/block_guess.py",
        "    while cap < asked:\n", "    while cap < asked // 2:\n",
        ("test_block_guess.py",),
        "a reading block's masked solve taken to fewer rows than the count it read"),
    Mutation(
        "reading-block-count-not-learnt", "block guesses",
        "torch_stsdic/movie/block_guess.py",
        "            self._learn(site, asked)\n", "            pass\n",
        ("test_block_guess.py",),
        "a reading block's count, read on the spot, not passed on to the next block's guess"),
    Mutation(
        "read-ahead-leaves-out-stored-frames", "frames", "torch_stsdic/movie/frames.py",
        "        order = [i for i in order if i not in self.entries]\n",
        "        order = [i for i in order if i not in self.entries and self._key(i) not in "
        "self.store]\n",
        ("test_frames.py",),
        "the read-ahead leaves out the frames the store holds when it is scheduled: those it "
        "drops later are read by the block loop"),
    Mutation(
        "passes-keep-no-frames", "frames", "torch_stsdic/movie/frames.py",
        "                    and kept + frame.nbytes <= self.keep_budget):",
        "                    and kept + frame.nbytes < 0):",
        ("test_frames.py",),
        "the store keeps none of the frames its passes share: a long movie's template "
        "prepares its frames again in every round"),
    Mutation(
        "template-shares-left-on-the-host", "template noise",
        "torch_stsdic/movie/template_noise.py",
        "        dev = share.device if device is None else torch.device(device)\n",
        "        dev = share.device\n",
        ("test_template_noise.py",),
        "the template's shares made on the host: a GPU run's every block copies them to the "
        "device, a wait each"),
    Mutation(
        "gradient-plane-checks-its-solve", "neighbour test", "torch_stsdic/analysis/quality.py",
        "    coef = torch.linalg.solve_ex(m, rhs).result\n",
        "    coef = torch.linalg.solve(m, rhs)\n",
        ("test_syncs.py",),
        "the neighbours' gradient plane solved with torch's error check: a wait for a GPU "
        "each round"),
    Mutation(
        "velocity-maps-by-a-decomposition", "velocity point",
        "torch_stsdic/movie/velocity_point.py",
        "sym2_pinv(m, 1e-9) @ rhs", "torch.linalg.pinv(m, rtol=1e-9) @ rhs",
        ("test_velocity_point.py",),
        "the velocity maps' 2 x 2 systems by torch's pinv: a decomposition that waits for a "
        "GPU"),
    Mutation(
        "later-rounds-blocked-as-carried", "reference", "torch_stsdic/movie/plan.py",
        "    return dataclasses.replace(plan, first_alone=False, "
        "batch_frames=max(plan.batch_frames, n))",
        "    return plan",
        ("test_series_reference.py",),
        "the template's later rounds in the carried run's blocks (first target alone, then 8): "
        "more blocks, each with its fixed costs"),
    Mutation(
        "native-noise-cut-excludes-its-own-level", "noise",
        "torch_stsdic/kernels/native/dic_kernels.cpp",
        "        const bool flat = sobel_at(p, w, i, j) <= c;",
        "        const bool flat = sobel_at(p, w, i, j) < c;",
        ("test_noise.py",),
        "the C++ noise estimate's flat pixels without those at the cut: another estimate "
        "than the torch code's"),
    Mutation(
        "gpu-walk-keeps-answers-of-rows-not-asked", "initial guess",
        "torch_stsdic/core/initial.py",
        "            better &= weak\n",
        "            better &= torch.ones_like(weak)\n",
        ("test_host_reads.py",),
        "a GPU's walk over weak frames keeps the better peaks of rows that were not weak: "
        "other first guesses than the CPU's"),
    Mutation(
        "unread-placement-skips-the-moved-rows-motion", "guessed reads",
        "torch_stsdic/movie/block_placement.py",
        "        self._centres_moved_masked(off, moved)\n",
        "        pass\n",
        ("test_block_guess.py",),
        "a placement taken unread keeps the shared motion at the POIs of the subsets it "
        "moved (not at their centres): other numbers than the reading way's"),
    Mutation(
        "unread-rescue-wave-size-unchecked", "guessed reads", "torch_stsdic/movie/rescue.py",
        "            self.defer_count(WAVE + str(w), answer[0], cap)\n",
        "            pass\n",
        ("test_block_guess.py",),
        "a rescue wave taken unread solves at most its capacity of rows and never checks "
        "that it found no more: rows left lost that the reading way rescues"),
    Mutation(
        "cache-padding-dropped-too-far", "solver", "torch_stsdic/core/gauss_newton.py",
        "                self.count = start + min(int(kept), end - start)\n",
        "                self.count = start\n",
        ("test_host_reads.py",),
        "the reference cache's padding taken back with the subsets before it (kept ones "
        "sampled again, or read past the kept rows)"),
    Mutation(
        "plane-rows-read-on-a-gpu", "neighbour test", "torch_stsdic/analysis/quality.py",
        "        if every_row or fit.numel() <= PLANE_EVERY_ROW:",
        "        if fit.numel() <= PLANE_EVERY_ROW:",
        ("test_quality.py",),
        "the gradients' plane fitted where needed, its rows read, where the caller asked for "
        "no read"),
    Mutation(
        "early-wrong-guess-redone-from-the-rescue", "block guesses",
        "torch_stsdic/movie/block_guess.py",
        "            if PLACEMENT in wrong.questions or wrong.whole:\n",
        "            if PLACEMENT in wrong.questions:\n",
        ("test_block_guess.py",),
        "a compacted solve of the block's own solve guessed wrong: only its rescue solved again"),
    Mutation(
        "block-after-the-reference-guesses", "block guesses", "torch_stsdic/movie/block.py",
        "    blk.guessing = guessing and carry is not None and carry.vel_known is None\n",
        "    blk.guessing = guessing\n",
        ("test_block_guess.py",),
        "a block whose carry lacks a velocity somewhere (after the reference frame's own "
        "row, after a block of one target) takes the last block's \"nothing lost\""),
    Mutation(
        "wrong-rescue-guess-keeps-its-state", "block guesses",
        "torch_stsdic/movie/block_guess.py",
        "            vars(self).update(state)\n", "            pass\n",
        ("test_block_guess.py",),
        "after a wrong guess of a rescue, the block goes on from what the wrong attempt left"),
    Mutation(
        "rescued-row-window-beyond-cap", "placement", "torch_stsdic/movie/block_placement.py",
        "            half = torch.minimum(half, self.window_cap[idx])\n",
        "            half = half\n",
        ("test_window_length.py",),
        "a rescued row near the border takes the longest window that stays in view, beyond "
        "what its point's motion supports"),
    Mutation(
        "mixed-windows-read-padding", "solver", "torch_stsdic/kernels/native/dic_kernels.cpp",
        "const int64_t nti = P.count ? std::min(std::max(P.count[i], int64_t(1)), nt) : nt;",
        "const int64_t nti = nt;",
        ("test_mixed_windows.py",),
        "a solve of windows of mixed length sums the padding frames of the shorter ones"),
    Mutation(
        "block-window-length-off-by-one", "movie", "torch_stsdic/movie/block_windows.py",
        "return self.planes[cols[h, b]], dts[h, b], 2 * m.long() + 1",
        "return self.planes[cols[h, b]], dts[h, b], 2 * m.long() + 3",
        ("test_mixed_windows.py",),
        "a block's one call for every window length solves each row with a window one frame "
        "too long on each side"),
    Mutation(
        "check-rounds-skip-a-window", "movie", "torch_stsdic/movie/checks.py",
        "            last[sel] = c\n", "            last[sel] = c + 1\n",
        ("test_mixed_windows.py",),
        "the model check's rounds of shorter windows skip each row's next candidate after a "
        "try"),
    Mutation(
        "window-test-independent-pool", "movie", "torch_stsdic/movie/window_length.py",
        "Z * DESIGN ** 0.5 * se", "Z * se", ("test_window_length.py",),
        "the window-length test's standard error takes the pooled terms as independent"),
    Mutation(
        "template-one-run", "movie", "torch_stsdic/movie/series_reference.py",
        "    n_runs = min(max(2, round(int(max_frames) / run)), len(ks) // run)\n",
        "    n_runs = min(int(max_frames) // run, len(ks) // run)\n",
        ("test_series_reference.py",),
        "a fixed long window's template and time-model test sample as many runs as the "
        "frames hold whole (none at m >= 4: no time-model test)"),
    Mutation(
        "carry-not-rounded-as-stored", "movie", "torch_stsdic/movie/row_writer.py",
        "    stored = as_stored_tensors(rows)\n", "    stored = rows\n",
        ("test_row_writer.py",),
        "the carry made on the device from the solved rows at full precision, not as the "
        "file stores them (a resumed run would carry other numbers)"),
    Mutation(
        "writer-drops-pending-blocks", "movie", "torch_stsdic/movie/row_writer.py",
        "                if self._error is None:  # after a failed write the rest are not "
        "written\n",
        "                if self._error is None and item[0][0] == 0:\n",
        ("test_row_writer.py", "test_series.py"),
        "the writer thread skips the blocks after the first (an interrupted run loses the "
        "blocks it had handed over)"),
    Mutation(
        "every-window-keeps-the-shortest", "checks", "torch_stsdic/movie/checks.py",
        'first = first.scatter_reduce(0, sel, torch.where(good, pos, n_pairs), "amin")',
        'first = first.scatter_reduce(0, sel, torch.where(good, pos, -1), "amax").clamp(0)\n'
        '        first = torch.where(first > 0, first, n_pairs)',
        ("test_mixed_windows.py",),
        "the model check's shorter windows tried at once (a GPU run's choice) keep each "
        "row's last passing window, not the longest"),
    Mutation(
        "rescue-skips-on-stale-facts", "rescue", "torch_stsdic/movie/rescue.py",
        "            if from_nb:\n                facts = self.read(self._facts(fft_tried))",
        "            if False:\n                facts = self.read(self._facts(fft_tried))",
        ("test_rescue.py", "test_series.py"),
        "the rescue's FFT steps sized by the facts read before the neighbours' step changed "
        "the rows"),
    Mutation(
        "fill-stops-after-one-ring", "carry", "torch_stsdic/movie/carry.py",
        "            if stop and not bool(fill.any()):",
        "            if stop and bool(fill.any()):",
        ("test_carry_shared.py",),
        "a carry's neighbour fill stops at the first ring that fills points, not at the "
        "first that fills none"),
    Mutation(
        "masked-groups-keep-every-row", "block windows", "torch_stsdic/movie/block_windows.py",
        "                where = key == window\n",
        "                where = key != 2\n",
        ("test_gpu_choices.py", "test_masked_solve.py"),
        "a masked group's solve keeps the rows of the other group too (a GPU run's "
        "classical rows overwritten by their window solve)"),
    Mutation(
        "masked-solve-iterates-every-row", "solver", "torch_stsdic/core/gauss_newton.py",
        "    live = ~low if active is None else active & ~low\n",
        "    live = ~low\n",
        ("test_masked_solve.py",),
        "a masked solve iterates the rows it was told to leave"),
    Mutation(
        "masked-check-keeps-dropped-rows", "row set", "torch_stsdic/movie/row_set.py",
        "            return RowSet(self.idx, True, self.act & keep), None\n",
        "            return RowSet(self.idx, True, self.act), None\n",
        ("test_row_set.py", "test_gpu_choices.py"),
        "the model check's masked steps (a GPU run's choice) keep the rows a step drops"),
    Mutation(
        "rescue-wave-placement-facts-misread", "rescue", "torch_stsdic/movie/rescue.py",
        "            facts, placed_facts = facts[:b + 2], facts[b + 2:]\n",
        "            facts, placed_facts = facts[:b + 2], facts[b + 1:]\n",
        ("test_gpu_choices.py",),
        "a rescue wave's border placement (made before the wave's read, a GPU run's "
        "choice) settled with the wrong facts"),
    Mutation(
        "median-test-one-round-on-gpu", "quality", "torch_stsdic/analysis/quality.py",
        "        if i == rounds - 1 or (until_done and not bool(cand.any())):\n",
        "        if i == rounds - 1 or not until_done or not bool(cand.any()):\n",
        ("test_quality.py", "test_gpu_choices.py"),
        "the neighbour test run to the end (a GPU run's choice) stops after its first "
        "round"),
)


def _copy(dst: Path) -> None:
    ignore = shutil.ignore_patterns(".git", "__pycache__", ".pytest_cache", "*.egg-info",
                                    ".ruff_cache", "stsdic-demo")
    shutil.copytree(REPO, dst, ignore=ignore, symlinks=True)


def _env(root: Path) -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(root) + os.pathsep + os.environ.get("PYTHONPATH", ""),
            "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "PYTHONDONTWRITEBYTECODE": "1"}


def run_one(mut: Mutation, timeout: float) -> dict[str, object]:
    """Apply ``mut`` in a fresh copy, run its tests; 'caught', 'SURVIVED' or 'STALE'."""
    src = (REPO / mut.path).read_text(encoding="utf-8")
    if src.count(mut.old) != 1:
        return {"result": "STALE", "detail": f"{mut.old!r} found {src.count(mut.old)} times",
                "seconds": 0.0}
    with tempfile.TemporaryDirectory(prefix="stsdic-mutant-") as tmp:
        root = Path(tmp) / "repo"
        _copy(root)
        shared = REPO.parent / "shared"
        if shared.is_dir():  # ../shared beside the copy too: the data tests run
            (Path(tmp) / "shared").symlink_to(shared, target_is_directory=True)
        (root / mut.path).write_text(src.replace(mut.old, mut.new), encoding="utf-8")
        env = _env(root)
        where = subprocess.run([sys.executable, "-c", "import torch_stsdic; "
                                "print(torch_stsdic.__file__)"], cwd=root, env=env,
                               capture_output=True, text=True)
        if not where.stdout.strip().startswith(str(root)):
            raise RuntimeError(f"the copy does not import its own package: {where.stdout!r} "
                               f"{where.stderr[-500:]}")
        cmd = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider",
               *[f"tests/{t}" for t in mut.tests]]
        t0 = time.monotonic()
        try:
            proc = subprocess.run(cmd, cwd=root, env=env, capture_output=True, text=True,
                                  timeout=timeout)
        except subprocess.TimeoutExpired:
            return {"result": "timeout", "detail": f"over {timeout:.0f} s",
                    "seconds": time.monotonic() - t0}
        seconds = time.monotonic() - t0
    lines = proc.stdout.strip().splitlines()
    if proc.returncode == 0:
        return {"result": "SURVIVED", "detail": lines[-1] if lines else "", "seconds": seconds}
    if proc.returncode not in (1,):  # 2: interrupted/collection error, 5: no tests
        return {"result": "error", "detail": "\n".join(lines[-5:]), "seconds": seconds}
    failed = [ln.split(" - ")[0].removeprefix("FAILED ") for ln in lines
              if ln.startswith("FAILED ")]
    return {"result": "caught", "detail": failed[0] if failed else lines[-1],
            "seconds": seconds}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", nargs="+", metavar="NAME", help="run these mutations only")
    ap.add_argument("--list", action="store_true", help="list the mutations and exit")
    ap.add_argument("--timeout", type=float, default=900.0, help="seconds per mutation")
    args = ap.parse_args(argv)
    muts = [m for m in MUTATIONS if not args.only or m.name in args.only]
    if args.only and len(muts) != len(args.only):
        known = {m.name for m in MUTATIONS}
        ap.error(f"unknown mutation(s): {sorted(set(args.only) - known)}")
    if args.list:
        for m in muts:
            print(f"{m.name:40s} {m.area:14s} {m.path}: {m.what}")
        return 0
    rows = []
    t0 = time.monotonic()
    for m in muts:
        r = run_one(m, args.timeout)
        rows.append((m, r))
        print(f"{m.name}: {r['result']} ({r['seconds']:.0f} s) {r['detail']}", flush=True)
    print()
    print("| mutation | area | file | result | caught by | time (s) |")
    print("|---|---|---|---|---|---|")
    for m, r in rows:
        by = r["detail"] if r["result"] == "caught" else f"({r['detail']})"
        print(f"| {m.name} | {m.area} | `{m.path.removeprefix('torch_stsdic/')}` | "
              f"{r['result']} | {by} | {r['seconds']:.0f} |")
    bad = [m.name for m, r in rows if r["result"] != "caught"]
    print(f"\n{len(rows) - len(bad)} of {len(rows)} mutations caught in "
          f"{time.monotonic() - t0:.0f} s" + (f"; not caught: {', '.join(bad)}" if bad else ""))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
