"""The one ``main()`` of our nodes: ``--help``, rclpy start-up, an EventsExecutor loop that stops
cleanly on SIGINT/SIGTERM, and an orderly shutdown.

rclpy 7.1's EventsExecutor hangs when ``rclpy.shutdown()`` runs in another thread (which is
what rclpy's own signal handler does) and ``spin_until_future_complete`` without a timeout
never returns. So rclpy's signal handlers stay off, ours only set a flag, and the executor is
spun in short ``spin_once`` slices that check it.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import signal
import sys
import threading
import time
from collections.abc import Callable, Collection, Iterator, Mapping, Sequence
from typing import Any

import rclpy
import yaml
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.exceptions import ParameterException
from rclpy.experimental import EventsExecutor
from rclpy.logging import get_logger
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from rclpy.task import Future
from rclpy.utilities import remove_ros_args

SPIN_SLICE = 0.1  # s, longest wait before the stop flag is looked at
WORK_SPIN_SLICE = 0.005  # s, the same with a main-thread ``work`` (it may wait this long for the spin lock)
CALLER_TURN = 0.0002  # s, the spin loop's poll while a main-thread caller holds or waits for the SpinLock


def parse_cli(prog: str, description: str, argv: Sequence[str], epilog: str | None = None) -> None:
    """Give the executable a ``--help`` (non-ROS arguments are refused); ROS arguments pass through."""
    parser = argparse.ArgumentParser(
        prog=prog,
        description=description,
        epilog=epilog or "Node parameters and remappings follow --ros-args, e.g. "
        "--ros-args -p mode:=realtime --params-file config/gear.yaml",
    )
    parser.parse_args(remove_ros_args(list(argv))[1:])


_command_line: list[str] | None = None  # run_node's argv (sys.argv when a node is made elsewhere)


def command_line_parameters(argv: Sequence[str], node_name: str) -> dict[str, str]:
    """The ``-p``/``--param`` values of ``argv``'s ROS arguments that reach node ``node_name``
    (``name:=value`` for every node, ``node:name:=value`` for this one), as written."""
    out: dict[str, str] = {}
    in_ros = False
    args = list(argv)
    for i, arg in enumerate(args):
        if arg == "--ros-args":
            in_ros = True
        elif arg == "--":
            in_ros = False
        elif in_ros and arg in ("-p", "--param") and i + 1 < len(args):
            target, sep, value = args[i + 1].partition(":=")
            if not sep:
                continue
            node, _, name = target.rpartition(":")
            if node in ("", node_name, "/" + node_name):
                out[name] = value
    return out


def _parse(raw: str) -> Any:
    """A ``-p`` value as rcl reads it: a number (``1e-3`` too, which YAML 1.1 leaves a string), a
    bool, a list of those, or the text."""
    for number in (int, float):
        try:
            return number(raw)
        except ValueError:
            pass
    try:
        value = yaml.safe_load(raw)
    except yaml.YAMLError:
        return raw
    if isinstance(value, list):
        return [_parse(v) if isinstance(v, str) else v for v in value]
    return value


def _same_value(actual: Any, given: Any) -> bool:
    if isinstance(actual, (list, tuple)) and isinstance(given, list):
        return len(actual) == len(given) and all(_same_value(a, g) for a, g in zip(actual, given, strict=True))
    if isinstance(actual, bool) or isinstance(given, bool):
        return actual is given
    if isinstance(actual, (int, float)) and isinstance(given, (int, float)):
        return float(actual) == float(given)
    return actual == given


def declare_read_only(node: Node, spec: Mapping[str, tuple[Any, str]], dynamic: Collection[str] = ()
                      ) -> dict[str, Any]:
    """Declare parameters ``name: (default, description)`` as read-only (fixed for the node's life)
    and return their values. Checking the values is the caller's job. The names in ``dynamic`` take
    a value of any type (a number or a list, ``0.5`` as well as ``[0.5, 0.3]``): their caller checks it.

    A ``-p`` on the command line that did not take effect is an error (``ValueError``), never
    silence: rcl drops a command-line value whose type differs from the one a ``--params-file``
    gives the same parameter (``-p franka_driver:reset_settle:=abc`` left the file's 200 in place)."""
    values = {}
    for name, (default, description) in spec.items():
        descriptor = ParameterDescriptor(description=description, read_only=True, dynamic_typing=name in dynamic)
        values[name] = node.declare_parameter(name, default, descriptor).value
    given = command_line_parameters(sys.argv if _command_line is None else _command_line, node.get_name())
    ignored = []
    for name, raw in given.items():
        if name not in values:
            continue
        if not _same_value(values[name], _parse(raw)):
            ignored.append(f"-p {node.get_name()}:{name}:={raw} (in effect: {values[name]!r})")
    if ignored:
        raise ValueError(f"command-line parameter(s) not applied: {'; '.join(ignored)}. ROS keeps the "
                         "parameters file's value when a -p value has another type than the file's")
    return values


def freeze_heap() -> int:
    """Collect once, then move every object alive now to the collector's permanent generation
    (``gc.freeze``); returns how many. For a process about to start a 1 kHz driver thread: a full
    collection walks every tracked object (about 110,000 after importing rclpy, MuJoCo, Pinocchio and
    the compiled kernels: ~40 ms here) with the GIL held, and stalls the tick for as long; after the
    freeze it walks only what was created since."""
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


class SpinLock:
    """What a node's main thread holds (``with node.spin_lock:``) for calls that must not interleave
    with the executor thread, which holds it for each spin slice. A waiting caller ends the
    executor's current wait and the spin loop lets it in before its next slice: with a plain
    ``Lock`` the loop took it straight back, and the learner waited 10-36 ms for each goal it sent.

    The wait ends through the slice's ``turn`` (spin with
    ``executor.spin_once_until_future_complete(turn, timeout)``): ``executor.wake()`` is not enough,
    rclpy 7.1's executors take their own wake-up as no work and wait again until the slice's timeout
    (a caller waited out the rest of each 5 ms slice, 2.4 ms in the median), and a guard condition of
    the node stops the EventsExecutor ("Guard conditions not supported")."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._callers = 0  # threads in or waiting for ``with``
        self._count = threading.Lock()  # guards _callers and _turn
        self._turn: Future | None = None  # of the slice being spun, done once a caller waits

    def __enter__(self) -> SpinLock:
        with self._count:
            self._callers += 1
            self._end_turn()
        self._lock.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self._lock.release()
        with self._count:
            self._callers -= 1

    def _end_turn(self) -> None:
        turn = self._turn
        if turn is not None and not turn.done():
            turn.set_result(True)  # its done callback wakes the executor, which then returns

    @contextlib.contextmanager
    def spin_slice(self) -> Iterator[Future]:
        """The executor thread's hold for one slice, after any waiting caller had its turn; yields
        the slice's turn (a future done as soon as a caller waits)."""
        while self._callers:
            time.sleep(CALLER_TURN)
        with self._lock:
            with self._count:
                self._turn = turn = Future()
                if self._callers:  # came in between: no wait at all
                    self._end_turn()
            try:
                yield turn
            finally:
                with self._count:
                    self._turn = None


def run_node(make_node: Callable[[], Node | Sequence[Node]], prog: str, description: str,
             argv: Sequence[str] | None = None,
             work: Callable[[Node, threading.Event], int] | None = None,
             make_executor: Callable[[], Any] = EventsExecutor, epilog: str | None = None,
             started: Callable[[list[Node]], None] | None = None) -> int:
    """Run one node (or several composed in this process, one executor) until SIGINT/SIGTERM.
    Returns the exit code (2 when a node refused its parameters).

    ``started(nodes)`` runs once the executor holds them (a composed driver starts its thread
    there); the nodes are destroyed in reverse order of creation.

    A node may define ``spin_pause() -> float``: seconds to sleep after each spin slice. rclpy 7.1
    resumes a coroutine that awaits a pending future at once, again and again, so while an action
    waits (for an episode, say) the executor thread spins without pause (``tests/test_ros_runtime.py``
    counts it). Alone that only burns a core; next to a driver thread it takes the GIL from the
    1 kHz tick. Our nodes no longer await anything that takes long (nf_controller sets up and runs
    its RunEpisode goals on timers), so none asks for a pause today.

    With ``work``, the executor spins in a background thread and ``work(node, stop)`` runs in the
    main thread; its return value is the exit code, and ``stop`` is set on a signal. If the node
    has a ``spin_lock`` (a ``SpinLock``, or any lock), each spin slice holds it, so the main thread can
    make calls that must not interleave with the executor (rclpy 7.1's ``ActionClient.send_goal_async``
    registers its request only after sending it: a fast response handled in between is dropped).
    """
    global _command_line
    argv = list(sys.argv if argv is None else argv)
    parse_cli(prog, description, argv, epilog)
    _command_line = argv
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    nodes: list[Node] = []
    executor = spinner = None
    try:
        try:
            made = make_node()
        except (ValueError, ParameterException) as exc:  # bad parameters: the node says which and why
            get_logger(prog).fatal(f"not starting: {exc}")
            return 2
        nodes = list(made) if isinstance(made, Sequence) else [made]
        node = nodes[0]
        executor = make_executor()
        for n in nodes:
            executor.add_node(n)
        if started is not None:
            started(nodes)

        lock = getattr(node, "spin_lock", None) or contextlib.nullcontext()
        slice_s = SPIN_SLICE if work is None else WORK_SPIN_SLICE
        pauses = [n.spin_pause for n in nodes if callable(getattr(n, "spin_pause", None))]

        def spin() -> None:
            while not stop.is_set() and rclpy.ok():
                if isinstance(lock, SpinLock):
                    with lock.spin_slice() as turn:
                        executor.spin_once_until_future_complete(turn, timeout_sec=slice_s)
                else:
                    with lock:
                        executor.spin_once(timeout_sec=slice_s)
                for pause in pauses:
                    seconds = pause()
                    if seconds > 0.0:
                        time.sleep(seconds)

        if work is None:
            spin()
            return 0
        spinner = threading.Thread(target=spin, name="ros-spin", daemon=True)
        spinner.start()
        return work(node, stop)
    finally:
        _command_line = None
        stop.set()
        if spinner is not None:
            spinner.join(timeout=2.0)
        if executor is not None:
            executor.shutdown()
        for n in reversed(nodes):
            n.destroy_node()
        rclpy.try_shutdown()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
