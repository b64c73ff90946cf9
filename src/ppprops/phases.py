"""Composing a run's phases: the proposers of its method (warm-up, the search phase, the selection
stage), the recording LLM client every request goes through, the request pacer and the prompt form,
and telling the proposers what the store holds.

``RunPhases`` is what a ``Study`` receives: it builds each part on first use (a process that only
tells a trial builds none), and the study calls it, never the parts' own constructors. The LLM
client's model (the configured endpoint, or the embedded model) is started on the first request and
closed with ``close``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from contextlib import AbstractContextManager, ExitStack, closing
from dataclasses import dataclass
from functools import cached_property, partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from . import seeding
from .client.codec import Codec
from .errors import ConfigError
from .events import RunEvents
from .methods import Method
from .store import RunStore
from .tasks import Task
from .values import Candidate, Trial

# The proposers, the prompt forms, the LLM client and the pacer are imported where they are used:
# `ppprops tell`, one process per trial, loads a study without them (tests/test_startup.py).
if TYPE_CHECKING:
    from .client.context import PromptSettings
    from .client.mechanisms import Mechanisms
    from .evaluation import Evaluator
    from .llm.pacing import Pacer
    from .llm.protocol import LLM
    from .llm.recording import RecordingLLM
    from .llm.settings import LLMConfig
    from .proposers.base import Phase
    from .wire.forms import PromptForm


@dataclass(frozen=True)
class PhaseSettings:
    """The run settings its phases depend on (``Study`` makes them from the run's config), never
    the whole config.

    ``warmup`` and ``iterations`` (the budget before and of the search phase), ``selection`` (the
    selection stage's candidates and episodes each, ``RunConfig.selection``), ``box`` (the public
    raw range of every parameter), ``mechanisms``, ``form`` (the resolved prompt form's name) and
    ``form_chosen`` (True: the user named it, so a model that cannot serve it is an error, not a
    fallback to chat), ``prompt_settings`` (a form's name -> the settings its prompts depend on),
    ``llm`` (the endpoint's settings), ``method_options`` (as stored; the method parses them),
    ``on_llm_failure``, ``parse_retries`` and ``parallel`` (P, the trials out at once);
    ``init_thetas``: the given policies the warm-up starts with (``warm_start``).
    """

    warmup: int
    iterations: int
    selection: tuple[int, int]
    box: tuple[float, float]
    mechanisms: Mechanisms
    form: str
    form_chosen: bool
    prompt_settings: Callable[[str], PromptSettings]
    llm: LLMConfig
    method_options: Mapping[str, Any] | None
    on_llm_failure: str
    parse_retries: int
    parallel: int
    init_thetas: tuple[tuple[float, ...], ...] = ()


class RunPhases:
    """The phases of one run and what they share, each built on first use.

    Args:
        settings: makes what the phases depend on of the run's configuration (``PhaseSettings``),
            called on first use (resolving the prompt form reads the forms, which a process that
            only tells a trial never loads).
        task, method, codec, streams: the study's task, method, codec and keyed random streams.
        store: the run's store (the recording client writes every request to it; the proposers are
            told its candidates).
        run_dir: the run directory (the embedded model's warm server is kept per directory).
        events: progress hooks (the embedded model's start, a one-time notice).
        evaluator: the episode runner of the task's env, made on first use (None: a task without an env).
        llm: the model to ask instead of the configured endpoint (the caller keeps and closes it).
        llm_gate: held around every LLM request (a grid's cap on concurrent requests).
        warm_llm: for the embedded model, the server kept warm for ``run_dir`` (``llm.embedded.WarmServer``).
    """

    def __init__(self, settings: Callable[[], PhaseSettings], *, task: Task, method: Method, codec: Codec, streams: seeding.Streams, store: RunStore,
                 run_dir: Path, events: RunEvents, evaluator: Callable[[], Evaluator] | None, llm: LLM | None = None,
                 llm_gate: AbstractContextManager[object] | None = None, warm_llm: bool = False) -> None:  # fmt: skip
        self._settings_of = settings
        self.task = task
        self.method = method
        self.codec = codec
        self.streams = streams
        self.store = store
        self.run_dir = run_dir
        self.events = events
        self.llm_given = llm
        self._evaluator = evaluator
        self._gate = llm_gate
        self._warm_llm = warm_llm
        self._stack = ExitStack()
        self._recording: RecordingLLM | None = None
        self._phases: list[Phase] | None = None
        self._told = 0  # every trial before it is settled and told to the proposers
        self._told_set: set[int] = set()  # candidates the proposers have been told
        self._failed_seen: set[int] = set()  # failed trials the proposers have heard of

    @cached_property
    def settings(self) -> PhaseSettings:
        """What the phases depend on of the run's configuration (made on first use)."""
        return self._settings_of()

    def phases(self) -> list[Phase]:
        """The run's phases in order (warm-up, the method's search phase, the selection stage), their
        proposers told every settled trial in the store, the search cut where a stop rule ended it
        (``cut_search``). Built on the first call."""
        if self._phases is None:
            self._phases = self._build()
            self._told, self._told_set, self._failed_seen = 0, set(), set()
            self.sync()
        from .proposers.selection import SelectionProposer
        from .stopping import search_end, stages

        past, end = stages(self.store), search_end(self.store)
        if not past and end is None:
            return self._phases
        episodes = self.settings.selection[1]
        return plan_phases(self._phases, past, end, lambda i: SelectionProposer(self.streams, episodes, stage=i))

    def _build(self) -> list[Phase]:
        from .proposers.base import Phase, SearchProposer, SearchSetup
        from .proposers.uniform import warmup_sampler
        from .strategies import search_phase
        from .wire.forms import FORMS

        settings, task = self.settings, self.task
        policy = task.policy
        mlp = {} if policy.is_linear else {"init": policy.init_bounds(task.n_s, task.n_a, settings.box),
                                           "bounds": policy.bounds(task.n_s, task.n_a, settings.box)}  # fmt: skip
        warmup: SearchProposer = warmup_sampler(task.D, settings.box, self.streams, settings.mechanisms, self.codec, **mlp)
        if settings.init_thetas:
            from .warm_start import GivenFirst

            warmup = GivenFirst(settings.init_thetas, warmup)
        phases = [Phase("warmup", warmup, settings.warmup)]
        if settings.iterations > 0:
            form = self.form() if self.method.uses_llm else FORMS[settings.form]
            notice = self.feedback_notice(form) if self.method.uses_llm else None
            if notice is not None:
                self.events.on_notice(notice)
            setup = SearchSetup(task=task, codec=self.codec, streams=self.streams, box=settings.box, warmup=settings.warmup,
                                iterations=settings.iterations, prompt=settings.prompt_settings(form.name), llm=settings.llm,
                                options=self.method.parse_options(settings.method_options), on_llm_failure=settings.on_llm_failure,
                                parse_retries=settings.parse_retries, llm_client=self.llm if self.method.uses_llm else None,
                                evaluator=self._evaluator() if self._evaluator is not None else None)  # fmt: skip
            phases.append(search_phase(self.method, setup))
        top, episodes = settings.selection
        if top:
            from .proposers.selection import SelectionProposer
            from .stopping import stages

            phases.append(Phase("selection", SelectionProposer(self.streams, episodes, stage=len(stages(self.store))), top))
        return phases

    def sync(self) -> None:
        """Tell every proposer the candidates recorded since it was last told (another process's
        too), in trial order, up to the first trial still out: a proposer's state is a function of
        the settled trials before it, the same in every process. A failed trial is never told as a
        candidate; the proposers hear that it failed (``SearchProposer.failed``: CMA-ES). The
        selection stage's re-evaluations are told to its proposer only. Nothing before the phases
        are built."""
        if self._phases is None:
            return
        out = [t.number for t in self.store.pending_trials()]
        upto = min(out) if out else None
        new = [c for c in self.store.candidates(since=self._told) if c.index not in self._told_set and (upto is None or c.index < upto)]
        failed = [t for t, _ in self.store.failed_trials() if t.number not in self._failed_seen and (upto is None or t.number < upto)]
        proposers = list(dict.fromkeys(ph.proposer for ph in self._phases))
        selecting = {id(ph.proposer) for ph in self._phases if ph.name == "selection"}  # re-evaluations are theirs alone
        events: list[tuple[int, Candidate | Trial]] = sorted([(c.index, c) for c in new] + [(t.number, t) for t in failed],
                                                             key=lambda e: e[0])
        for _, item in events:
            if isinstance(item, Candidate):
                for p in proposers:
                    if item.reevaluates is None or id(p) in selecting:  # a search continued after its selection stage never sees them
                        p.tell(item)
                self._told_set.add(item.index)
            else:
                for p in proposers:
                    p.failed(item)
                self._failed_seen.add(item.number)
        while self._told in self._told_set or self._told in self._failed_seen:  # the settled prefix, read no more
            self._told += 1

    def last_latency(self) -> float | None:
        """Seconds of the search phase's latest LLM call (None before the first, or when it sends none)."""
        search = [p for p in self._phases or [] if p.name not in ("warmup", "selection")]
        return search[0].proposer.latency() if search else None

    def llm(self) -> RecordingLLM:
        """The run's recording LLM client, over the model given or the configured one (``llm.client.connect``:
        nothing is started before the first request)."""
        if self._recording is None:
            from .llm.recording import RecordingLLM

            model = self.llm_given
            if model is None:
                from .llm.client import connect

                model = self._stack.enter_context(closing(connect(self.settings.llm, gate=self._gate, on_loading=self.events.on_llm_loading,
                                                                  on_ready=self.events.on_llm_ready, server=self._server())))
            self._recording = RecordingLLM(model, self.store, on_first_use=self.store.begin_llm_session, pacer=self.pacer())
        return self._recording

    def _server(self) -> Callable[[], AbstractContextManager[Any]] | None:
        """The embedded model's server to start for this run (None: ``connect``'s own choice)."""
        if not self.settings.llm.embedded:
            return None
        parallel = self.settings.parallel
        slots = {"slots": parallel} if parallel > 1 else {}  # a round's P requests decoded together
        if self._warm_llm:
            from .llm.embedded import WarmServer

            return partial(WarmServer, self.run_dir, context_size=self.settings.llm.context_size, **slots)
        if slots:
            from .llm.embedded import EmbeddedServer

            return partial(EmbeddedServer, context_size=self.settings.llm.context_size, **slots)
        return None

    def pacer(self) -> Pacer | None:
        """The request pacer when ``pace_requests`` is on (``llm.pacing``): its jitter keyed by the
        secrets, its floor the longest time between two warm-up trials (told back to back)."""
        if not self.settings.mechanisms.pace_requests:
            return None
        from .llm.pacing import Pacer

        def floor() -> float:
            times = [t[3] for t in self.store.candidate_times() if t[1] in ("warmup", "init")]
            return max(np.diff(times), default=0.0) if len(times) > 1 else 0.0

        return Pacer(self.store, lambda n: self.streams.rng(seeding.PACING, n), floor=floor)

    def feedback_notice(self, form: PromptForm) -> str | None:
        """The line a run says once when the prompt form will not show the detailed feedback the
        settings ask for (a form whose entries show returns only)."""
        declared = self.task.detailed_feedback()
        if form.shows_feedback or not self.settings.mechanisms.detailed_feedback or not declared:
            return None
        return (f"the {form.name} form (the embedded model's default) shows the LLM the returns only, not the detailed feedback "
                f"of this task ({declared}); --prompt-form chat shows it")

    def form(self) -> PromptForm:
        """The prompt form the proposer uses: ``config.form``, except that ``auto`` falls back to chat
        for a model that cannot continue documents (a form it cannot serve, chosen explicitly: ConfigError)."""
        from .wire.forms import CHAT, ENDPOINT_COMPLETIONS, FORMS

        form = FORMS[self.settings.form]
        if form.endpoint == ENDPOINT_COMPLETIONS and ENDPOINT_COMPLETIONS not in self.llm().endpoints:
            if self.settings.form_chosen:
                raise ConfigError(f"--prompt-form {form.name} needs a model that continues documents (the completions "
                                  "endpoint); this one serves chat only: use --prompt-form chat or auto")
            return CHAT
        return form

    def release_llm(self) -> None:
        """Close the LLM client (stopping an embedded server it started); a later request starts a new one."""
        self._stack.close()
        self._recording = None

    def stop_warm_server(self) -> None:
        """Stop the embedded model's server kept warm for the run directory (``ppprops ask``), if
        any, letting go of it first when this run uses it (stopping waits for every process using it)."""
        from .llm.embedded import stop_warm_server

        if self._warm_llm:
            self.release_llm()
        stop_warm_server(self.run_dir)

    def close(self) -> None:
        """Close the LLM client, as ``release_llm``."""
        self.release_llm()


def plan_phases(built: list[Phase], past: Sequence[tuple[int, int]], end: int | None,
                past_selection: Callable[[int], Any]) -> list[Phase]:
    """The run's phases laid end to end by trial number, where its search was continued after a
    selection stage or cut by a stop rule (``ppprops.stopping``).

    ``built``: the warm-up, the search phase and the selection stage as ``RunPhases`` builds them;
    ``past``: (trial number where it began, its trials) of each earlier selection stage, after
    which the search went on (``resume`` with a larger limit); ``end``: where a stop rule ended the
    search now (None: it runs its budget). The warm-up and the search phase fill the numbers
    between the stages, each going on from its own next iteration (``Phase.offset``); each
    earlier stage is a phase of ``past_selection(i)``'s proposer (its trials are all asked: it
    proposes nothing more); the last stage follows the search.
    """
    from .proposers.base import Phase

    searching = [ph for ph in built if ph.name != "selection"]
    out: list[Phase] = []
    used = [0] * len(searching)

    def fill(k: int) -> None:
        for i, ph in enumerate(searching):
            take = min(ph.budget - used[i], k)
            if take > 0:
                out.append(Phase(ph.name, ph.proposer, take, offset=used[i]))
                used[i], k = used[i] + take, k - take

    number = 0
    for stage, (first, top) in enumerate(past):
        fill(first - number)
        if top:
            out.append(Phase("selection", past_selection(stage), top))
        number = first + top
    fill(end - number if end is not None else sum(ph.budget for ph in searching))
    out.extend(ph for ph in built if ph.name == "selection")
    return out
