"""rocoma_can/workers.py: WorkerManager: real threads on the monotonic clock; counts and orderings,
no wall-time limits."""
from __future__ import annotations

import logging
import os
import threading
import time

import pytest

from rocoma_can.interfaces import Controller
from rocoma_can.workers import WorkerEvent, WorkerHandle, WorkerManager, WorkerOptions

WAIT = 5.0  # generous bound for every wait: the 2 cores are shared with other test runs


def wait_until(predicate, timeout: float = WAIT) -> bool:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.002)
    return True


def thread_names() -> set[str]:
    return {t.name for t in threading.enumerate()}


@pytest.fixture
def workers():
    manager = WorkerManager("ctrl")
    yield manager
    assert manager.cancel_all(timeout=WAIT)
    assert not any(name.startswith("ctrl/") for name in thread_names())


class Recorder:
    """A callback that records its events and stops after ``limit`` calls (None: never)."""

    def __init__(self, limit: int | None = None, result: object = True) -> None:
        self.events: list[WorkerEvent] = []
        self.threads: list[str] = []
        self.limit = limit
        self.result = result

    def __call__(self, event: WorkerEvent) -> object:
        self.events.append(event)
        self.threads.append(threading.current_thread().name)
        if self.limit is not None and len(self.events) >= self.limit:
            return False
        return self.result


def test_periodic_worker_runs_on_absolute_deadlines(workers):
    rec = Recorder()
    frequency = 200.0
    handle = workers.add_worker(WorkerOptions("pub", rec, frequency=frequency))
    assert not handle.is_running and rec.events == []
    assert workers.start_worker(handle)
    assert wait_until(lambda: len(rec.events) >= 20)
    assert workers.cancel_worker(handle, timeout=WAIT)
    events = list(rec.events)
    assert [e.iteration for e in events] == list(range(len(events)))
    assert {e.name for e in events} == {"pub"}
    assert set(rec.threads) == {"ctrl/pub"}
    # Never called before its deadline: call k comes no earlier than k periods after call 0.
    period = 1.0 / frequency
    for e in events:
        assert e.time - events[0].time >= e.iteration * period - 1e-3


def test_once_worker_runs_exactly_once(workers):
    rec = Recorder()
    handle = workers.add_worker(WorkerOptions("once", rec, autostart=True))
    assert wait_until(lambda: not handle.is_running)
    assert len(rec.events) == 1 and rec.events[0].iteration == 0
    assert workers.active_workers == []


def test_callback_false_ends_the_worker(workers):
    rec = Recorder(limit=3)
    handle = workers.add_worker(WorkerOptions("three", rec, frequency=500.0, autostart=True))
    assert wait_until(lambda: not handle.is_running)
    assert [e.iteration for e in rec.events] == [0, 1, 2]
    assert "ctrl/three" not in thread_names()


def test_callback_returning_none_ends_with_a_hint(workers, caplog):
    rec = Recorder(result=None)
    handle = workers.add_worker(WorkerOptions("forgot", rec, frequency=500.0, autostart=True))
    assert wait_until(lambda: not handle.is_running)
    assert len(rec.events) == 1
    assert any("returned None" in r.getMessage() and r.levelno == logging.WARNING
               for r in caplog.records)


def test_exception_ends_the_worker_and_is_logged_once(workers, caplog):
    calls = []

    def boom(event: WorkerEvent) -> bool:
        calls.append(event.iteration)
        if event.iteration == 2:
            raise RuntimeError("sensor gone")
        return True

    with caplog.at_level(logging.ERROR, logger="rocoma_can.workers"):
        handle = workers.add_worker(WorkerOptions("boom", boom, frequency=500.0, autostart=True))
        assert wait_until(lambda: not handle.is_running)
    assert calls == [0, 1, 2]
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1
    assert "ctrl/boom" in errors[0].getMessage()
    assert errors[0].exc_info is not None and "sensor gone" in str(errors[0].exc_info[1])


def test_cancel_wakes_a_sleeping_worker_at_once(workers):
    rec = Recorder()
    # Period 1000 s: without the cancel Event the join below could only time out.
    handle = workers.add_worker(WorkerOptions("slow", rec, frequency=0.001, autostart=True))
    assert wait_until(lambda: len(rec.events) == 1)
    assert "ctrl/slow" in thread_names()
    assert workers.cancel_worker("slow", wait=True, timeout=WAIT)
    assert not handle.is_running
    assert "ctrl/slow" not in thread_names()
    assert len(rec.events) == 1


def test_cancel_without_wait_then_the_worker_ends(workers):
    handle = workers.add_worker(WorkerOptions("w", Recorder(), frequency=0.001, autostart=True))
    assert workers.cancel_worker(handle, wait=False)
    assert wait_until(lambda: not handle.is_running)


def test_a_stuck_worker_is_reported_not_waited_on(workers, caplog):
    release = threading.Event()
    entered = threading.Event()

    def stuck(event: WorkerEvent) -> bool:
        entered.set()
        release.wait(WAIT)
        return True

    handle = workers.add_worker(WorkerOptions("stuck", stuck, frequency=10.0, autostart=True))
    assert entered.wait(WAIT)
    with caplog.at_level(logging.ERROR, logger="rocoma_can.workers"):
        assert workers.cancel_worker(handle, timeout=0.05) is False
    assert handle.is_running
    assert any("ctrl/stuck" in r.getMessage() and "did not end" in r.getMessage()
               for r in caplog.records)
    release.set()
    assert workers.cancel_worker(handle, timeout=WAIT)


def test_a_worker_may_cancel_itself(workers):
    results = []

    def selfish(event: WorkerEvent) -> bool:
        results.append(workers.cancel_worker("selfish", wait=True, timeout=WAIT))
        return True

    handle = workers.add_worker(WorkerOptions("selfish", selfish, frequency=100.0,
                                              autostart=True))
    assert wait_until(lambda: not handle.is_running)
    assert results == [True]


def test_autostart_and_start_rules(workers, caplog):
    auto = Recorder()
    handle = workers.add_worker(WorkerOptions("auto", auto, frequency=100.0, autostart=True))
    assert wait_until(lambda: len(auto.events) >= 1)
    assert workers.active_workers == ["auto"]
    assert workers.start_worker("auto") is False  # already running
    assert any("already running" in r.getMessage() for r in caplog.records)

    manual = Recorder()
    workers.add_worker(WorkerOptions("manual", manual, frequency=100.0))
    assert workers.active_workers == ["auto"]
    assert manual.events == []
    assert workers.start_worker("manual")
    assert wait_until(lambda: workers.active_workers == ["auto", "manual"])
    assert workers.cancel_all(timeout=WAIT)
    assert workers.active_workers == []
    assert not handle.is_running


def test_restart_after_cancel_counts_from_zero(workers):
    rec = Recorder()
    handle = workers.add_worker(WorkerOptions("re", rec, frequency=200.0, autostart=True))
    assert wait_until(lambda: len(rec.events) >= 3)
    assert workers.cancel_worker(handle, timeout=WAIT)
    first_run = len(rec.events)
    assert workers.start_worker(handle)
    assert wait_until(lambda: len(rec.events) >= first_run + 3)
    assert workers.cancel_worker(handle, timeout=WAIT)
    assert rec.events[first_run].iteration == 0


def test_names_are_reusable_only_after_the_worker_ended(workers):
    workers.add_worker(WorkerOptions("dup", Recorder(), frequency=0.001, autostart=True))
    with pytest.raises(ValueError, match="ctrl/dup.*already running"):
        workers.add_worker(WorkerOptions("dup", Recorder()))
    assert workers.cancel_worker("dup", timeout=WAIT)
    rec = Recorder()
    second = workers.add_worker(WorkerOptions("dup", rec, autostart=True))
    assert wait_until(lambda: not second.is_running)
    assert len(rec.events) == 1


def test_unknown_or_foreign_workers(workers, caplog):
    assert workers.start_worker("nope") is False
    assert workers.cancel_worker("nope") is False
    assert any("not registered" in r.getMessage() for r in caplog.records)
    other = WorkerManager("other").add_worker(WorkerOptions("x", Recorder()))
    assert isinstance(other, WorkerHandle)
    assert workers.start_worker(other) is False
    with pytest.raises(TypeError, match="WorkerHandle or a worker name"):
        workers.start_worker(3)
    with pytest.raises(ValueError, match="timeout"):
        workers.cancel_worker("nope", timeout=-1.0)


def test_priority_gets_sched_fifo_or_a_warning(workers, caplog):
    policies = []

    def probe(event: WorkerEvent) -> bool:
        policies.append(os.sched_getscheduler(0))  # 0: the calling thread
        return True

    with caplog.at_level(logging.WARNING, logger="rocoma_can.workers"):
        handle = workers.add_worker(WorkerOptions("rt", probe, priority=1, autostart=True))
        assert wait_until(lambda: not handle.is_running)
    if handle.realtime:  # permitted (root / CAP_SYS_NICE): only this thread is real-time
        assert policies == [os.SCHED_FIFO]
    else:
        assert handle.realtime is False and policies == [os.SCHED_OTHER]
        assert any("SCHED_FIFO" in r.getMessage() for r in caplog.records)
    assert os.sched_getscheduler(0) == os.SCHED_OTHER


def test_priority_refused_logs_a_warning_and_runs_normally(workers, caplog, monkeypatch):
    # The one fake: we cannot drop privileges in-process, so refuse like the kernel would.
    def refuse(pid, policy, param):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    rec = Recorder(limit=3)
    with caplog.at_level(logging.WARNING, logger="rocoma_can.workers"):
        handle = workers.add_worker(WorkerOptions("rt", rec, frequency=500.0, priority=50,
                                                  autostart=True))
        assert wait_until(lambda: not handle.is_running)
    assert handle.realtime is False
    assert len(rec.events) == 3
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1
    assert "ctrl/rt" in warnings[0] and "SCHED_FIFO priority 50" in warnings[0]


def test_priority_without_platform_support_logs_a_warning(workers, caplog, monkeypatch):
    monkeypatch.delattr(os, "sched_setscheduler")
    with caplog.at_level(logging.WARNING, logger="rocoma_can.workers"):
        handle = workers.add_worker(WorkerOptions("rt", Recorder(), priority=1, autostart=True))
        assert wait_until(lambda: not handle.is_running)
    assert handle.realtime is False
    assert any("does not offer" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize("kwargs, field", [
    (dict(name=""), "name"),
    (dict(name="a/b"), "name"),
    (dict(name=3), "name"),
    (dict(callback="not callable"), "callback"),
    (dict(frequency=-1.0), "frequency"),
    (dict(frequency=float("nan")), "frequency"),
    (dict(frequency=float("inf")), "frequency"),
    (dict(frequency="10"), "frequency"),
    (dict(priority=-1), "priority"),
    (dict(priority=100), "priority"),
    (dict(priority=1.5), "priority"),
    (dict(priority=True), "priority"),
    (dict(autostart="yes"), "autostart"),
])
def test_bad_options_name_the_field(kwargs, field):
    args = dict(name="w", callback=Recorder())
    args.update(kwargs)
    with pytest.raises(ValueError, match=rf"WorkerOptions\.{field}"):
        WorkerOptions(**args)


def test_add_worker_needs_options(workers):
    with pytest.raises(TypeError, match="WorkerOptions"):
        workers.add_worker({"name": "w"})


class Publisher(Controller):
    """rocoma's example: start a worker in initialize, cancel it in pre_stop."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.published = 0
        self.handle: WorkerHandle | None = None

    def _publish(self, event: WorkerEvent) -> bool:
        self.published += 1
        return True

    def initialize(self, dt: float) -> bool:
        self.handle = self.add_worker(WorkerOptions("publish", self._publish, frequency=100.0))
        return self.start_worker(self.handle)

    def advance(self, dt: float) -> bool:
        return True

    def pre_stop(self) -> bool:
        return self.cancel_worker(self.handle, wait=True)


def test_controller_delegates_to_its_worker_manager():
    ctrl = Publisher("pub")
    with pytest.raises(RuntimeError, match="no worker manager"):
        ctrl.initialize(0.01)
    ctrl.workers = WorkerManager(ctrl.name)
    assert ctrl.initialize(0.01)
    assert wait_until(lambda: ctrl.published >= 2)
    assert "pub/publish" in thread_names()
    assert ctrl.pre_stop()
    assert "pub/publish" not in thread_names()
    assert ctrl.workers.active_workers == []
