"""Loop verification in the tracking process or on the run's executor (:class:`~fpp_graph.types.PairVerifier`).

Odometry is sequential (each frame needs the last keyframe), but a keyframe's loop candidates
are independent registrations: :class:`ExecutorVerifier` sends them to the run's worker
processes while tracking goes on. The keyframe manager applies their results a fixed number
of keyframes later in submission order (:data:`~fpp_graph.slam.keyframes.VERIFY_LAG_KEYFRAMES`), so a run gives the same
loops, poses and map with either verifier and any number of workers.
"""

from __future__ import annotations

from concurrent.futures import Executor, Future

import numpy as np
from numpy.typing import NDArray

from fpp_graph.config import Config
from fpp_graph.slam.frame_store import FrameStore
from fpp_graph.slam.sources import FrameSource
from fpp_graph.slam.workers import verify_pair
from fpp_graph.types import Constraint, ConstraintKind, PairRegistrar


class InlineVerifier:
    """Registers each pair in this process when it is submitted (the future is already done).

    For runs without worker processes and for stores that keep frames in memory only.
    """

    def __init__(self, registrar: PairRegistrar, store: FrameStore) -> None:
        self.registrar = registrar
        self.store = store

    def submit(self, target_id: int, source_id: int, T_guess: NDArray[np.float64] | None, kind: ConstraintKind) -> Future[Constraint]:
        future: Future[Constraint] = Future()
        try:
            future.set_result(self.registrar.register(self.store.get(target_id), self.store.get(source_id), T_guess, kind=kind))
        except Exception as exc:  # delivered where the result is read, like an executor's
            future.set_exception(exc)
        return future


class ExecutorVerifier:
    """Registers pairs in worker processes started by :func:`fpp_graph.slam.workers.init_worker`.

    Both frames are read there from the store's folder (they are keyframes, so the store has
    written them), and only paths, the initial guess and the resulting Constraint are pickled.
    Workers the run did not start (Dask) get the frame ``source`` with each task and adopt it
    once per ``token`` (see :func:`fpp_graph.slam.workers.decode_to_cache`). The run's ``config``
    goes with each task too: it names the registrar the workers make (``plugins.registrar``).
    """

    def __init__(
        self, executor: Executor, store: FrameStore, source: FrameSource | None = None, token: str | None = None,
        config: Config | None = None,
    ) -> None:
        if store.directory is None:
            raise ValueError("ExecutorVerifier needs a FrameStore with a directory: workers read the frames from it")
        self.executor = executor
        self.store = store
        self.source, self.token, self.config = source, token, config

    def submit(self, target_id: int, source_id: int, T_guess: NDArray[np.float64] | None, kind: ConstraintKind) -> Future[Constraint]:
        return self.executor.submit(
            verify_pair, str(self.store.path_of(target_id)), str(self.store.path_of(source_id)), T_guess, str(ConstraintKind(kind)),
            self.source, self.token, self.config,
        )
