"""The pose stage's batched work on two cores: half of each batch of poses in a helper process, bitwise as on one.

Most of the pose stage scores and refines batches of poses (hundreds of seeds screened, tens refined in full), and
every row of those batches is computed on its own: `evaluate_offsets` and `refine_hypotheses` give a pose the same
numbers whatever other poses share its batch, with one exception: the refinement stops when every pose's step is
below its tolerance, so a pose iterates as long as the slowest pose of its batch. A `SplitExecutor` writes the
second half of a batch to a helper process (`yoto.localize.helper.LocalizerProcess`: the one that localizes a
pair's right contact, holding the object model and building its surface field there once), computes the first half
itself meanwhile, and joins the two. Each half counts the Gauss-Newton iterations it ran (the field's gradient
reads); when both ran as many the joined batch is what one process computes (each half stopped at the first
iteration where all of its poses were below the tolerance, and none earlier, so the whole batch stops there too);
otherwise the caller refines the whole batch again itself, which is rare (see docs/journal/pose.md) and costs only time.
The joint search's key test (`search.key_matches`) is split the same way, by rows of left locations cut between two
of its chunks, each chunk tested on its own: the same pairs in the same order; and so are the closed-form poses of
its matches (`solver.closed_form_quaternions`, ~3 ms for 8,000 matches: every row on its own, numpy's and BLAS's
arithmetic the same whatever rows share the call, checked bitwise on 120 cuts of 30 searches, docs/journal/pose.md).

Small batches stay in the calling process (`SplitConfig`): both halves pay a refinement's fixed cost (~0.2 ms since
its iterations run compiled), and a round trip through the helper's pipe 20-70 us. Without a
helper (`LOCAL`) everything runs in the calling process, as it always did.

    with LocalizerProcess(localizer) as helper:
        prepare_pose_helper(helper, model).result()
        estimate = estimate_pose(pair, model, localizer, config, helper)
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from yoto.contacts import WorldContact
from yoto.localize.helper import LocalizerProcess, Pending
from yoto.objects.model import ObjectModel
from yoto.pose.field import FieldConfig, SurfaceField, surface_field
from yoto.pose.refine import CalibrationPrior, ContactPoints, RefineConfig, Refined, evaluate_offsets, refine_hypotheses
from yoto.pose.search import KeyTest, Matched, key_matches
from yoto.pose.solver import closed_form_quaternions
from yoto.registration import one_blas_thread


@dataclass(frozen=True)
class SplitConfig:
    """When the pose stage's batches are split between the calling process and its helper."""

    min_poses: int = 16  # refinements of fewer poses stay in the calling process (see docs/journal/pose.md) ...
    min_scored: int = 1000  # ... and cheap scores (`evaluate_offsets`, ~1 us a pose) of fewer ...
    min_key_pairs: int = 400_000  # ... and the search's key tests (`search.key_matches`) of fewer location pairs
    min_closed_form: int = 2000  # ... and closed-form poses (~0.36 us each) of fewer matches
    helper_share: float = 0.5  # share of a split batch the helper computes
    max_wait_share: float = 0.5  # a split after which this process waited for the helper's half longer than this
    # share of the time its own half took finds no free core for the helper (it ran when this process waited) ...
    slow_splits: int = 2  # ... and after this many of them the rest of the pose stage stays in this process


class LocalExecutor:
    """The pose stage's batched work in the calling process (what `pose_from_candidates` does without a helper)."""

    def offsets(
        self,
        field: SurfaceField,
        contacts: list[ContactPoints],
        T_world_object: np.ndarray,
        prior: CalibrationPrior,
        config: RefineConfig,
    ) -> np.ndarray:
        """`refine.evaluate_offsets`."""
        return evaluate_offsets(field, contacts, T_world_object, prior, config)

    def refine(
        self,
        field: SurfaceField,
        contacts: list[ContactPoints],
        T_world_object: np.ndarray,
        prior: CalibrationPrior,
        config: RefineConfig,
        corrections_start: np.ndarray | None = None,
    ) -> Refined:
        """`refine.refine_hypotheses` (each pose's sensor corrections starting from `corrections_start` where given)."""
        return refine_hypotheses(field, contacts, T_world_object, prior, config, corrections_start)

    def key_matches(self, test: KeyTest) -> Matched:
        """`search.key_matches` on all of the search's location pairs."""
        return key_matches(test)

    def closed_form(self, *arguments: Any) -> tuple[np.ndarray, np.ndarray]:
        """`solver.closed_form_quaternions` (object-side (K, 3) points and normals of both contacts, the measured
        pair) of all K matches."""
        return closed_form_quaternions(*arguments)


LOCAL = LocalExecutor()


class SplitExecutor(LocalExecutor):
    """The pose stage's batches split between the calling process and `helper` (one object model, one field)."""

    def __init__(
        self,
        helper: LocalizerProcess,
        model: ObjectModel,
        field_config: FieldConfig,
        config: SplitConfig = SplitConfig(),
    ):
        self.helper = helper
        self.model = model
        self.field_config = field_config
        self.config = config
        self.split = 0  # refinements split between the two processes ...
        self.redone = 0  # ... and of those, refined again whole here (the halves ran different iteration counts)
        self.helper_extra_cpu_ms = 0.0  # CPU time by which the helper's halves outlasted this process's halves:
        # this process's CPU time plus this is the stage's wall time on two free cores (round trips aside)
        self.slow = 0  # splits that found no free core for the helper (SplitConfig.max_wait_share)

    def _cut(self, count: int, least: int) -> int | None:
        """Where a batch of `count` poses is cut (the caller's share before it), or None to keep it here."""
        if count < max(least, 2) or self.slow >= self.config.slow_splits:
            return None
        return min(max(int(round(count * (1.0 - self.config.helper_share))), 1), count - 1)

    def offsets(
        self,
        field: SurfaceField,
        contacts: list[ContactPoints],
        T_world_object: np.ndarray,
        prior: CalibrationPrior,
        config: RefineConfig,
    ) -> np.ndarray:
        cut = self._cut(len(T_world_object), self.config.min_scored)
        if cut is None:
            return evaluate_offsets(field, contacts, T_world_object, prior, config)
        here, there = self._field_halves(evaluate_offsets, cut, field, contacts, T_world_object, prior, config)
        return np.concatenate([here, there])

    def refine(
        self,
        field: SurfaceField,
        contacts: list[ContactPoints],
        T_world_object: np.ndarray,
        prior: CalibrationPrior,
        config: RefineConfig,
        corrections_start: np.ndarray | None = None,
    ) -> Refined:
        cut = self._cut(len(T_world_object), self.config.min_poses)
        if cut is None:
            return refine_hypotheses(field, contacts, T_world_object, prior, config, corrections_start)
        (here, iterations), (there, iterations_there) = self._field_halves(
            _counted_refine, cut, field, contacts, T_world_object, prior, config, corrections_start
        )
        self.split += 1
        if iterations != iterations_there:  # the whole batch would have iterated on past the half that stopped first
            self.redone += 1
            return refine_hypotheses(field, contacts, T_world_object, prior, config, corrections_start)
        return joined(here, there)

    def key_matches(self, test: KeyTest) -> Matched:
        """The left locations' rows cut between two chunks, the first part tested here and the rest in the helper:
        the same pairs in the same order as all rows at once (each chunk is tested on its own)."""
        rows, chunk = test.rows, test.chunk
        cut = int(round(rows * (1.0 - self.config.helper_share) / chunk)) * chunk
        if self._cut(rows * test.right_columns.shape[1], self.config.min_key_pairs) is None or not 0 < cut < rows:
            return key_matches(test)
        (i, j, mismatch), (i_there, j_there, mismatch_there) = self._halves(
            lambda: key_matches(test, 0, cut), _remote_key_matches, test, cut
        )
        return np.concatenate([i, i_there]), np.concatenate([j, j_there]), np.concatenate([mismatch, mismatch_there])

    def closed_form(
        self,
        p_left_object: np.ndarray,
        n_left_object: np.ndarray,
        p_right_object: np.ndarray,
        n_right_object: np.ndarray,
        left_world: WorldContact,
        right_world: WorldContact,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The matches' rows cut in two, the closed-form poses of the first part here and of the rest in the helper:
        each row's pose is computed on its own, so the joined arrays are those of all rows at once."""
        world = (left_world, right_world)
        cut = self._cut(len(p_left_object), self.config.min_closed_form)
        if cut is None:
            return closed_form_quaternions(p_left_object, n_left_object, p_right_object, n_right_object, *world)
        here, there = slice(None, cut), slice(cut, None)
        (quaternions, translations), (quaternions_there, translations_there) = self._halves(
            lambda: closed_form_quaternions(
                p_left_object[here], n_left_object[here], p_right_object[here], n_right_object[here], *world
            ),
            _remote_closed_form,
            p_left_object[there],
            n_left_object[there],
            p_right_object[there],
            n_right_object[there],
            *world,
        )
        return np.concatenate([quaternions, quaternions_there]), np.concatenate([translations, translations_there])

    def _field_halves(
        self,
        local: Callable[..., Any],
        cut: int,
        field: SurfaceField,
        contacts: list[ContactPoints],
        T_world_object: np.ndarray,
        prior: CalibrationPrior,
        config: RefineConfig,
        *per_pose: np.ndarray | None,
    ) -> tuple[Any, Any]:
        """`local` (a module-level function of the field and these arguments) on the poses before `cut` here, and
        on the rest in the helper meanwhile (with the helper's field). `per_pose`: further arguments with a row per
        pose (or None), cut as the poses are."""
        return self._halves(
            lambda: local(field, contacts, T_world_object[:cut], prior, config, *_rows(per_pose, slice(None, cut))),
            _remote_half,
            self.field_config,
            local,
            contacts,
            T_world_object[cut:],
            prior,
            config,
            *_rows(per_pose, slice(cut, None)),
        )

    def _halves(self, here: Callable[[], Any], remote: Callable[..., tuple[Any, float]], *arguments: Any) -> Any:
        """`here()` in this process while the helper runs `remote(model, *arguments)` (which returns its result
        and its CPU time in ms); both results. Records the helper's CPU time beyond this process's, and whether
        this process then waited long for the helper (no free core)."""
        pending = self.helper.call(remote, self.model, *arguments)
        tick, start = time.process_time(), time.perf_counter()
        mine = here()
        done = time.perf_counter()
        there, helper_cpu_ms = pending.result()
        self.helper_extra_cpu_ms += max(0.0, helper_cpu_ms - 1000.0 * (time.process_time() - tick))
        self.slow += time.perf_counter() - done > self.config.max_wait_share * (done - start)
        return mine, there


def joined(first: Refined, second: Refined) -> Refined:
    """Two sets of refined poses as one."""
    return Refined(*(np.concatenate([getattr(first, n), getattr(second, n)]) for n in first.__dataclass_fields__))


def prepare_pose_helper(
    helper: LocalizerProcess, model: ObjectModel, field_config: FieldConfig = FieldConfig()
) -> Pending:
    """Send `model` to the helper and let it build its surface field now, while this process goes on (`result()`
    waits for it): the first pose of an object then does not wait for it (`LocalizerProcess.prepare_object`
    prepares the localizer's per-model data)."""
    return helper.call(_remote_field, model, field_config)


class _CountingField(SurfaceField):
    """A surface field that counts the reads with a gradient (one per contact and Gauss-Newton iteration)."""

    def __init__(self, field: SurfaceField):  # the same grid and lookup tables, no copy
        self.__dict__.update(field.__dict__)
        self.gradient_reads = 0

    def distance(self, points_object: np.ndarray, with_gradient: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        self.gradient_reads += with_gradient
        return super().distance(points_object, with_gradient)

    def count_gradient_reads(self, count: int) -> None:  # the refinement's compiled reads (`pose.kernels`)
        self.gradient_reads += count


def _counted_refine(
    field: SurfaceField,
    contacts: list[ContactPoints],
    T_world_object: np.ndarray,
    prior: CalibrationPrior,
    config: RefineConfig,
    corrections_start: np.ndarray | None = None,
) -> tuple[Refined, int]:
    """`refine_hypotheses` and how many field reads with a gradient it made (its iterations times the contacts)."""
    counting = _CountingField(field)
    refined = refine_hypotheses(counting, contacts, T_world_object, prior, config, corrections_start)
    return refined, counting.gradient_reads


def _rows(arrays: tuple[np.ndarray | None, ...], rows: slice) -> list[np.ndarray | None]:
    """The `rows` of each array (None stays None)."""
    return [None if array is None else array[rows] for array in arrays]


def _remote_field(model: ObjectModel, field_config: FieldConfig) -> None:
    surface_field(model, field_config)


def _remote_half(
    model: ObjectModel, field_config: FieldConfig, local: Callable[..., Any], *arguments: Any
) -> tuple[Any, float]:
    """The helper's half of a batch: `local` (`evaluate_offsets`, `_counted_refine`) with the helper's field, and
    its CPU time (ms)."""
    return _timed(lambda: local(surface_field(model, field_config), *arguments))


def _remote_key_matches(model: ObjectModel, test: KeyTest, first: int) -> tuple[Matched, float]:
    """The helper's rows of the search's key test (from `first` on), and its CPU time (ms)."""
    return _timed(lambda: key_matches(test, first))


def _remote_closed_form(model: ObjectModel, *arguments: Any) -> tuple[tuple[np.ndarray, np.ndarray], float]:
    """The helper's rows of the search's closed-form poses, and its CPU time (ms)."""
    return _timed(lambda: closed_form_quaternions(*arguments))


def _timed(work: Callable[[], Any]) -> tuple[Any, float]:
    """`work()` in the helper with BLAS on one thread, as the calling process's pose stage runs (sums in one order,
    so the halves join bitwise), and its CPU time (ms)."""
    tick = time.process_time()
    with one_blas_thread():
        result = work()
    return result, 1000.0 * (time.process_time() - tick)
