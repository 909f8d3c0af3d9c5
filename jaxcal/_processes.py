"""A process's place among those of a distributed run (`jaxcal.distributed` joins one), and what
batch work needs from the others beyond JAX's own sharding: its share of the items, what every
process found, and a meeting point. Imports no JAX until asked (the command line's parser reads
`jaxcal.distributed`)."""

import dataclasses
import pickle


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
        collective: a process may arrive hours after another (its share took longer)."""
        if self.count == 1:
            return [obj]
        client, step = _client(), _next("gather")
        client.key_value_set_bytes(f"jaxcal/{step}/{self.index}", pickle.dumps(obj))
        return [
            pickle.loads(client.blocking_key_value_get_bytes(f"jaxcal/{step}/{i}", WAIT_MS))
            for i in range(self.count)
        ]

    def meet(self, what: str) -> None:
        """Wait until every process is here (`what` names the place, for the runtime's errors).
        Before a compiled program's first collective: XLA's CPU collectives give the processes
        30 s to join one, and one process may compile for longer than that."""
        if self.count > 1:
            _client().wait_at_barrier(f"jaxcal/{_next(what)}", WAIT_MS)


#: How long a process waits for the others (a day): a process that died is reported sooner, by
#: the runtime's heartbeat.
WAIT_MS = 24 * 3600 * 1000
_STEPS: dict[str, int] = {}


def _next(what: str) -> str:
    """`what` and how many times this process has asked for it: the same on every process."""
    _STEPS[what] = _STEPS.get(what, 0) + 1
    return f"{what}/{_STEPS[what]}"


def _client():
    """The runtime's client (JAX's own key-value store and barriers; no public name yet)."""
    from jax._src import distributed

    return distributed.global_state.client


ONE = Processes()


def current() -> Processes:
    """This process's place in a distributed run already joined (`ONE` where there is none)."""
    import jax

    if not jax.distributed.is_initialized():
        return ONE
    return Processes(jax.process_index(), jax.process_count())
