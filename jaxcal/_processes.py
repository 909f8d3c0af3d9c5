"""A process's place among those of a distributed run (`jaxcal.distributed` joins one), and what
batch work needs from the others beyond JAX's own sharding: its share of the items, what every
process found, and a meeting point. Imports no JAX until asked (the command line's parser reads
`jaxcal.distributed`)."""

import contextlib
import dataclasses
import pickle
import sys
import time

from .errors import JaxcalError


@dataclasses.dataclass(frozen=True)
class Processes:
    """This process's place among those of a run: `index` of `count` (`ONE`: a run of one)."""

    index: int = 0
    count: int = 1

    @property
    def first(self) -> bool:
        return self.index == 0

    def share(self, n: int) -> range:
        """This process's items of `n` (dealt round-robin: item k to process k mod count)."""
        return range(self.index, n, self.count)

    def gather(self, obj) -> list:
        """`obj` of every process, in process order, on every process (any picklable object;
        every process calls it, as many times). Through the runtime's key-value store, not a
        collective: a process may arrive hours after another (its share took longer). **Raises**
        `PeerError` where another process stopped instead (`fail`)."""
        if self.count == 1:
            return [obj]
        client, step = _client(), _next("gather")
        client.key_value_set_bytes(f"jaxcal/{step}/{self.index}", pickle.dumps(obj))
        got: dict[int, object] = {}
        while len(got) < self.count:
            for i in range(self.count):
                if i not in got:
                    with contextlib.suppress(Exception):  # not there yet
                        got[i] = pickle.loads(client.key_value_try_get_bytes(f"jaxcal/{step}/{i}"))
            if len(got) < self.count:
                self.check()
                time.sleep(POLL_S)
        return [got[i] for i in range(self.count)]

    def check(self) -> None:
        """**Raises** `PeerError` if another process stopped (`fail`): between items of a share."""
        if self.count > 1:
            stopped = _client().key_value_dir_get_bytes("jaxcal/stopped/")
            if stopped:
                key, why = stopped[0]
                raise PeerError(f"process {key.rsplit('/', 1)[1]} of {self.count} stopped: {why.decode()}")

    def meet(self, what: str) -> None:
        """Wait until every process is here (`what` names the place). Before a compiled
        program's first collective: XLA's CPU collectives give the processes 30 s to join one,
        and one process may compile for longer than that."""
        if self.count > 1:
            self.gather(what)

    def fail(self, why: str) -> None:
        """Tell the other processes that this one stopped (`why`), so that they stop too instead
        of waiting for it (`gather`); the first lingers a moment, as it holds the runtime."""
        if self.count == 1:
            return
        with contextlib.suppress(Exception):  # the runtime itself may be what failed
            _client().key_value_set_bytes(f"jaxcal/stopped/{self.index}", why.encode(), allow_overwrite=True)
            if self.first:
                time.sleep(4 * POLL_S)


class PeerError(JaxcalError):
    """Another process of a distributed run stopped (its reason in the message)."""


#: How often a waiting process looks for the others (s).
POLL_S = 0.2
_STEPS: dict[str, int] = {}


def _next(what: str) -> str:
    """`what` and how many times this process has asked for it: the same on every process."""
    _STEPS[what] = _STEPS.get(what, 0) + 1
    return f"{what}/{_STEPS[what]}"


def _client():
    """The runtime's client (JAX's own key-value store; no public name yet)."""
    from jax._src import distributed

    return distributed.global_state.client


ONE = Processes()


def current() -> Processes:
    """This process's place in a distributed run already joined (`ONE` where there is none; JAX
    is not imported for the answer: a run is joined by importing it)."""
    jax = sys.modules.get("jax")
    if jax is None or not jax.distributed.is_initialized():
        return ONE
    return Processes(jax.process_index(), jax.process_count())
