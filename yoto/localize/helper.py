"""A localizer in a helper process, so that a pair's two contacts are localized at once, one per core.

Threads cannot do this: most of a contact's time goes to numpy operations on small arrays (tens of candidates,
tens of points), and each holds Python's GIL for its call; only the k-d tree lookups and the matrix products run
without it. Two threads localizing the two contacts of a pair took 45 ms where one after the other took 55 ms
(docs/journal/localization.md). A process has its own interpreter: the helper localizes one contact while the calling
process localizes the other.

The helper is started once (spawn: a fresh interpreter, safe beside the threads of BLAS and torch) with a copy of
the localizer. It receives each object model once and keeps the last `models_kept` of them, with whatever the
localizer caches per model (the matched filter's anchor maps are built again there: the first contact of an
object costs the same seconds in the helper as in the caller; `prepare_object` does it ahead of time). After
that a contact costs its transfer: the tactile cloud (~0.5 MB) and the candidates back, 0.05-0.2 ms of CPU to
pickle. The calling thread writes a request to the helper's pipe itself, then goes on with its own contact: no
background thread of this process has to win the GIL from it before the helper can start.
The pose stage uses the same helper for half of its batches of poses (`call`, `yoto.pose.executor`): one helper
process per session serves both.
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
from collections.abc import Callable
from dataclasses import dataclass, replace
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from yoto.contacts import TactileContact, contact_in_world
from yoto.errors import YotoError
from yoto.localize.base import ContactLocalizer, localize_cloud
from yoto.objects.model import ObjectModel

MODELS_KEPT = 4  # object models the helper keeps by default (the caches of yoto.objects.cache keep as many)


@dataclass
class Pending:
    """A request written to the helper; `result()` waits for its answer (and raises what the helper raised)."""

    helper: LocalizerProcess
    number: int

    def result(self) -> Any:
        return self.helper._answer(self.number)


class LocalizerProcess:
    """A copy of `localizer` in a helper process; `submit` localizes one contact there while the caller works."""

    def __init__(self, localizer: ContactLocalizer, models_kept: int = MODELS_KEPT):
        context = multiprocessing.get_context("spawn")
        self._connection, child = context.Pipe()
        self._process = context.Process(target=_serve, args=(child, localizer, models_kept), daemon=True)
        self._process.start()
        child.close()
        self._models_kept = models_kept
        self._sent: OrderedDict[str, None] = OrderedDict()  # mirrors the helper's models (same order, same limit)
        self._lock = threading.Lock()
        self._requested = 0  # requests written to the helper ...
        self._received = 0  # ... and answers read back
        self._answers: dict[int, tuple[bool, Any]] = {}  # answers read back and not yet collected, by request

    def prepare_object(self, model: ObjectModel) -> None:
        """Send the model and let the helper's localizer build its per-model data now (waits for it)."""
        self._request("prepare", model).result()

    def submit(self, contact: TactileContact, model: ObjectModel, truth_p_object: np.ndarray | None = None) -> Pending:
        """Localize one contact in the helper. The answer's `result()`: its candidates, its world-side measurement
        (`contact_in_world`) and the helper's time for the candidates (ms)."""
        return self._request(
            "localize", model, contact.points_sensor, contact.T_world_sensor, truth_p_object, contact.depth_scale_sigma
        )

    def call(self, function: Callable[..., Any], model: ObjectModel, *arguments: Any) -> Pending:
        """Run `function(model, *arguments)` in the helper, `model` being its copy there (sent once, as for
        `submit`). `function` is pickled by name: a module-level function (the pose stage's halves of its batches,
        `yoto.pose.executor`); the answer's `result()` is what it returns."""
        return self._request("call", model, function, arguments)

    def close(self) -> None:
        """Stop the helper process (after the request it is working on, if any)."""
        with self._lock:
            if self._connection.closed:
                return
            if self._process.is_alive():
                self._connection.send(None)
            self._process.join(timeout=10)
            self._connection.close()

    def __enter__(self) -> LocalizerProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _request(self, kind: str, model: ObjectModel, *arguments: Any) -> Pending:
        with self._lock:
            # One request in flight at a time: an earlier answer is read first, so that the helper never waits to
            # write an answer while this process waits to write a request.
            self._read_answers(self._requested)
            key = model.fingerprint
            to_send = None if key in self._sent else replace(model)  # a fresh instance: no k-d tree, mesh, ray caster
            self._connection.send((kind, key, to_send, arguments))  # pickled whole before anything is written
            if to_send is not None:
                self._sent[key] = None
                while len(self._sent) > self._models_kept:
                    self._sent.popitem(last=False)
            self._requested += 1
            return Pending(self, self._requested)

    def _answer(self, number: int) -> Any:
        with self._lock:
            self._read_answers(number)
            succeeded, value = self._answers.pop(number)
        if not succeeded:
            raise value
        return value

    def _read_answers(self, number: int) -> None:
        """Read answers off the pipe until that of request `number` is in (they come back in order)."""
        while self._received < number:
            try:
                answer = self._connection.recv()
            except EOFError as error:
                raise YotoError("the localizer's helper process ended without answering") from error
            self._received += 1
            self._answers[self._received] = answer


def _serve(connection: Connection, localizer: ContactLocalizer, models_kept: int) -> None:
    """The helper process: answer requests in order until told to stop (None) or the caller is gone."""
    models: OrderedDict[str, ObjectModel] = OrderedDict()
    while True:
        try:
            request = connection.recv()
        except (EOFError, KeyboardInterrupt):  # the caller is gone, or Ctrl-C reached its whole process group
            return
        if request is None:
            return
        kind, key, model, arguments = request
        if model is not None:  # (re)sent: now the newest, as in the caller's record
            models.pop(key, None)
            models[key] = model
            while len(models) > models_kept:
                models.popitem(last=False)
        try:
            answer: tuple[bool, Any] = (True, _run(localizer, kind, models[key], arguments))
        except Exception as error:  # the caller raises it
            answer = (False, error)
        try:
            connection.send(answer)
        except Exception as error:  # an answer that does not pickle
            connection.send((False, YotoError(f"the localizer's helper could not send its answer back: {error!r}")))


def _run(localizer: ContactLocalizer, kind: str, model: ObjectModel, arguments: tuple) -> Any:
    if kind == "prepare":
        prepare = getattr(localizer, "prepare_object", None)
        if prepare is not None:
            prepare(model)
        return None
    if kind == "call":
        function, function_arguments = arguments
        return function(model, *function_arguments)
    points_sensor, T_world_sensor, truth_p_object, depth_scale_sigma = arguments
    tick = time.perf_counter()
    candidates = localize_cloud(localizer, points_sensor, model, truth_p_object, depth_scale_sigma)
    milliseconds = 1000.0 * (time.perf_counter() - tick)
    return candidates, contact_in_world(TactileContact(points_sensor, T_world_sensor)), milliseconds
