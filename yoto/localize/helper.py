"""A localizer in a helper process, so that a pair's two contacts are localized at once, one per core.

Threads cannot do this: most of a contact's time goes to numpy operations on small arrays (tens of candidates,
tens of points), and each holds Python's GIL for its call; only the k-d tree lookups and the matrix products run
without it. Two threads localizing the two contacts of a pair took 45 ms where one after the other took 55 ms
(docs/localization.md). A process has its own interpreter: the helper localizes one contact while the calling
process localizes the other.

The helper is started once (spawn: a fresh interpreter, safe beside the threads of BLAS and torch) with a copy of
the localizer. It receives each object model once and keeps the last `MODELS_KEPT` of them, with whatever the
localizer caches per model (the matched filter's anchor maps are built again there: the first contact of an
object costs the same seconds in the helper as in the caller; `prepare_object` does it ahead of time). After
that a contact costs its transfer (the tactile cloud, ~0.5 MB, and the candidates back: about a millisecond).
A script that starts one needs the usual `if __name__ == "__main__":` guard of spawned processes.

    with LocalizerProcess(localizer) as helper:
        helper.prepare_object(model)
        candidates, world, latency = localize_contacts(pair, model, localizer, helper)
"""

from __future__ import annotations

import multiprocessing
import threading
import time
from collections import OrderedDict
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import replace

import numpy as np

from yoto.contacts import ContactEstimate, TactileContact, WorldContact, contact_in_world
from yoto.localize.base import ContactLocalizer
from yoto.objects.model import ObjectModel

MODELS_KEPT = 4  # object models the helper keeps (the caches of yoto.objects.cache keep as many)

# In the helper process: its localizer and the models it was sent, by fingerprint, oldest first.
_localizer: ContactLocalizer | None = None
_models: OrderedDict[str, ObjectModel] = OrderedDict()


class LocalizerProcess:
    """A copy of `localizer` in a helper process; `submit` localizes one contact there while the caller works."""

    def __init__(self, localizer: ContactLocalizer):
        self._pool = ProcessPoolExecutor(
            max_workers=1, mp_context=multiprocessing.get_context("spawn"), initializer=_start, initargs=(localizer,)
        )
        self._sent: OrderedDict[str, None] = OrderedDict()  # mirrors the helper's models (same order, same limit)
        self._lock = threading.Lock()

    def prepare_object(self, model: ObjectModel) -> None:
        """Send the model and let the helper's localizer build its per-model data now (waits for it)."""
        with self._lock:
            future = self._pool.submit(_prepare, model.fingerprint, self._model_to_send(model))
        try:
            future.result()
        except BaseException:
            self._forget(model.fingerprint)
            raise

    def submit(
        self, contact: TactileContact, model: ObjectModel, truth_p_object: np.ndarray | None = None
    ) -> Future[tuple[list[ContactEstimate], WorldContact, float]]:
        """Localize one contact in the helper: a future of its candidates, its world-side measurement
        (`contact_in_world`) and the helper's time for the candidates (ms)."""
        with self._lock:
            future = self._pool.submit(
                _localize,
                model.fingerprint,
                self._model_to_send(model),
                contact.points_sensor,
                contact.T_world_sensor,
                truth_p_object,
            )
        future.add_done_callback(lambda done: self._forget(model.fingerprint) if done.exception() else None)
        return future

    def close(self) -> None:
        """Stop the helper process (waits for the contact it is localizing, if any)."""
        self._pool.shutdown()

    def __enter__(self) -> LocalizerProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _model_to_send(self, model: ObjectModel) -> ObjectModel | None:
        """The model, stripped of its cached derived data, when the helper does not hold it; else None. The
        helper's requests run in the order they were sent, so this record of what it holds stays exact."""
        key = model.fingerprint
        if key in self._sent:
            return None
        self._sent[key] = None
        while len(self._sent) > MODELS_KEPT:
            self._sent.popitem(last=False)
        return replace(model)  # a fresh instance: k-d tree, mesh and ray caster are rebuilt on use there

    def _forget(self, key: str) -> None:
        """After a failed request: send the model again next time (it may not have arrived)."""
        with self._lock:
            self._sent.pop(key, None)


def _start(localizer: ContactLocalizer) -> None:
    global _localizer
    _localizer = localizer


def _model(key: str, model: ObjectModel | None) -> ObjectModel:
    """The helper's copy of a model: the one just sent (kept), or the one kept from before."""
    if model is not None:
        _models.pop(key, None)  # (re)sent: now the newest, as in the caller's record
        _models[key] = model
        while len(_models) > MODELS_KEPT:
            _models.popitem(last=False)
    return _models[key]


def _prepare(key: str, model: ObjectModel | None) -> None:
    kept = _model(key, model)
    prepare = getattr(_localizer, "prepare_object", None)
    if prepare is not None:
        prepare(kept)


def _localize(
    key: str,
    model: ObjectModel | None,
    points_sensor: np.ndarray,
    T_world_sensor: np.ndarray,
    truth_p_object: np.ndarray | None,
) -> tuple[list[ContactEstimate], WorldContact, float]:
    kept = _model(key, model)
    assert _localizer is not None
    tick = time.perf_counter()
    candidates = _localizer.localize(points_sensor, kept, truth_p_object)
    milliseconds = 1000.0 * (time.perf_counter() - tick)
    return candidates, contact_in_world(TactileContact(points_sensor, T_world_sensor)), milliseconds
