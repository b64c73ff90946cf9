"""The study: one search's composition root, with a public ask/tell (pycma's ``OOOptimizer``,
Optuna's ``Study``).

A ``Study`` owns the run directory's store, the secrets and the codec, the random streams, the
proposers of the method's phases, the LLM client's lifecycle (started on the first LLM ask,
closed with the study) and the recording client every request goes through, and the policy file.
Everything else is a short loop over it:

    study = Study.create(config, run_dir)          # or Study.load(run_dir)
    while not study.done:
        trial = study.ask()                        # raw theta, W, b, the episode seeds to use
        feedback = evaluate(trial)                 # on a simulator, a real robot, anything
        study.tell(trial, returns, components=..., diagnostics=...)
    study.finalize()                               # final evaluation, policy file

``optimize`` is that loop with the task's env (``ppprops run``, ``resume``, ``search()``, grid
runs, the black-box baselines); a robot outside Python drives the same loop through
``ppprops ask`` / ``ppprops tell``.

Crash safety: ``ask`` stores the trial before it returns it (the ``pending`` table), so after a
crash or a restart ``ask`` returns the same trial again without asking the LLM twice; ``tell``
records the candidate and clears the trial in one transaction. ``ask`` and ``tell`` hold a file
lock (``locks.STUDY_LOCK``): a second process asking while the first waits for the LLM blocks,
then gets the same pending trial. Feedback told is raw; encoding (paper Eq. 5, 7-8) happens here.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from contextlib import AbstractContextManager
from dataclasses import replace
from functools import partial
from pathlib import Path
from time import time
from typing import TYPE_CHECKING, Any, overload

import numpy as np

from . import seeding, stopping
from .client.codec import Codec
from .client.hardening import codec_for
from .client.secrets import Secrets
from .config import RunConfig
from .errors import ConfigError, StudyComplete, TrialsOut
from .evaluation import Evaluator, Fleet
from .events import NO_EVENTS, RunEvents
from .finalizing import env_final_episodes, final_evaluation, finish_status, provenance, write_policy
from .locks import STUDY_LOCK, file_lock
from .loop import search_candidates, select_best
from .methods import Method, get_method
from .naming import check_worker, holders
from .phases import PhaseSettings, RunPhases
from .rundir import create_run, load_run
from .scheduling import check_left, check_retry, held, propose, wait_for
from .status import RunStatus
from .store import RunStore
from .tasks import Task
from .told import check_failed_alone, check_teller, failure_reason, not_pending, told_candidate
from .values import Candidate, Feedback, FinalEval, Trial

# What only asking a new trial, the env-driven loop or the policy needs (the proposers, the prompt
# forms, the LLM client, the policy file) is imported where it is used: `ppprops tell` and
# `ppprops ask`, one process per trial, load a study without them (tests/test_startup.py).
if TYPE_CHECKING:
    from .llm.protocol import LLM
    from .policy_file import Policy
    from .proposers.base import Phase

Callback = Callable[[Candidate, "Study"], "bool | None"]

class Study:
    """One search in one run directory, with a public ask/tell (module docstring).

    Made by ``Study.create`` (a new run directory) or ``Study.load`` (an existing one); use it in a
    ``with`` block, which closes the store, the LLM client and the env.

    Args:
        run_dir: the run directory.
        store: its open store (the study closes it).
        config: the run's stored configuration.
        secrets: the run's secrets (its key file).
        llm: the model to ask instead of the configured endpoint (an ``llm.protocol.LLM``; the
            caller keeps and closes it). None: the configured endpoint, or the embedded model,
            started on the first LLM request and closed with the study.
        llm_gate: held around every LLM request (a grid's cap on concurrent requests).
        events: progress hooks (the embedded model's start, the final evaluation).
        warm_llm: for the embedded model, use the server kept warm for this study directory
            (``llm.embedded.WarmServer``: started by the first process that needs it, left
            running for the next, stopped when idle or by ``finalize``) instead of one started
            and stopped with this study object (``ppprops ask``, one process per trial).
        env: an env of the task made already (``runner.check_startable`` makes it before the run
            directory exists): the episodes run on it, and the study closes it.
    """

    def __init__(self, run_dir: Path, store: RunStore, config: RunConfig, secrets: Secrets, *, llm: LLM | None = None,
                 llm_gate: AbstractContextManager[object] | None = None, events: RunEvents = NO_EVENTS,
                 warm_llm: bool = False, env: Any = None) -> None:  # fmt: skip
        self.run_dir = Path(run_dir)
        self.store = store
        self.config = config
        self.secrets = secrets
        self.task: Task = config.make_task()
        self.method: Method = get_method(config.method)
        self.codec: Codec = codec_for(secrets, self.task, config.encoding)
        self.streams = seeding.Streams(config.seed, secrets.subkey("streams") if store.streams_keyed() else None)
        self.events = events
        self._evaluator: Evaluator | None = None
        self._env = env
        self._phases = RunPhases(partial(_phase_settings, config, self.has_env), task=self.task, method=self.method, codec=self.codec,
                                 streams=self.streams, store=store, run_dir=self.run_dir, events=events, llm=llm, llm_gate=llm_gate,
                                 evaluator=(lambda: self.evaluator) if self.has_env else None, warm_llm=warm_llm)  # fmt: skip

    # -- making and opening -------------------------------------------------------------------
    @classmethod
    def create(cls, config: RunConfig, run_dir: Path, *, secrets: Secrets | None = None, **kwargs: Any) -> Study:
        """A new study in ``run_dir`` (``rundir.create_run``: the directory appears atomically,
        with its key file and store), status ``open``. ``secrets`` replaces freshly drawn ones
        (tests, grids); ``kwargs`` as for the constructor. Raises ConfigError for bad settings or
        an occupied ``run_dir``."""
        store, secrets = create_run(config, run_dir, secrets)
        try:
            stored = RunConfig.from_json(store.config())  # with the task's declaration
            store.set_status(RunStatus.OPEN)  # nobody runs it yet: ask/tell, or optimize (which says running)
            return cls(run_dir, store, stored, secrets, **kwargs)
        except BaseException:
            store.close()
            raise

    @classmethod
    def load(cls, run_dir: Path, **kwargs: Any) -> Study:
        """The study of an existing run directory, as it was left (``kwargs`` as for the constructor).

        Raises:
            StoreError: not a run directory, or a damaged store.
            KeyFileError: the key file is missing, damaged or foreign.
            ConfigError: the stored config names a task or method unknown here, or an RL baseline run.
        """
        store, config, secrets = load_run(Path(run_dir))
        try:
            return cls(Path(run_dir), store, config, secrets, **kwargs)
        except BaseException:
            store.close()
            raise

    def close(self) -> None:
        """Close the LLM client (stopping an embedded server), the env and the store."""
        try:
            self._phases.close()
            if self._evaluator is not None:
                self._evaluator.close()
                self._evaluator = None
            if self._env is not None:  # given and never used
                self._env.close()
                self._env = None
        finally:
            self.store.close()

    def __enter__(self) -> Study:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return (f"Study(run_dir={str(self.run_dir)!r}, task={self.task.name!r}, method={self.method.name!r}, "
                f"trials={self.store.candidate_count()}/{self.total})")

    # -- where it stands ----------------------------------------------------------------------
    @property
    def has_env(self) -> bool:
        """True when the task has an env ppprops can run (False: a robot outside Python)."""
        return bool(self.task.has_env)

    @property
    def total(self) -> int:
        """The study's budget of trials: warm-up, search phase (up to where a stop rule ended it,
        ``stopping.search_end``) and the selection stage's re-evaluations."""
        end = stopping.search_end(self.store)
        return (self._planned_end if end is None else end) + self.config.selection(self.has_env)[0]

    @property
    def _planned_end(self) -> int:
        return stopping.planned_end(self.store, self.config.warmup, self.config.iterations)

    def _check_stop(self, *, told: bool) -> None:
        """Check the stop rules (``stopping.update``): one that fires ends the search here."""
        delay = partial(stopping.keyed_delay, self.streams, self.store) if self.config.mechanisms.hardened else None
        why = stopping.update(self.store, self.config.stop, planned_end=self._planned_end, now=time(), told=told, delay=delay)
        if why is not None:  # it ended now
            self.events.on_notice(f"the search stopped: {why}")
            self.events.on_start(self.store.candidate_count() + self.store.failed_count(), self.total)

    @property
    def trials(self) -> list[Candidate]:
        """Every told trial, in order: raw and encoded parameters and feedback (``values.Candidate``)."""
        return self.store.candidates()

    @property
    def pending(self) -> Trial | None:
        """The first trial asked for and not yet told (the lowest number), or None."""
        trial = self.store.pending_trial()
        return None if trial is None else self._with_policy(trial)

    def _with_policy(self, trial: Trial) -> Trial:
        """A stored trial with the study's policy family (the store keeps theta, n_s and n_a; a
        trial's ``policy`` is None for the paper's linear policy)."""
        return trial if self.task.policy.is_linear else replace(trial, policy=self.task.policy)

    @property
    def out(self) -> list[Trial]:
        """Every trial asked for and not yet told, by number, each with the worker holding it (``Trial.worker``)."""
        return self._pending_trials()

    def _pending_trials(self) -> list[Trial]:
        """The stored pending trials, by number, with the study's policy family (``_with_policy``)."""
        return [self._with_policy(t) for t in self.store.pending_trials()]

    @property
    def status(self) -> tuple[RunStatus, str]:
        """``(status, reason)`` as stored (``status.RunStatus``)."""
        return self.store.run_status()

    @property
    def done(self) -> bool:
        """True when nothing is left to ask: the budget is spent, or the search stopped on purpose
        (a pending trial still has to be told)."""
        if self.store.pending_trial() is not None:
            return False
        if self.status[0] in (RunStatus.STOPPED, RunStatus.FINISHED):
            return True
        return self.store.next_number() >= self.total

    @property
    def best(self) -> Candidate | None:
        """The search candidate to hand over (``loop.select_best``: after the selection stage, the
        best mean over all its episodes; before it, the best search-time return), None before any."""
        cands = self.store.candidates()
        return select_best(cands) if search_candidates(cands) else None

    # -- ask / tell ---------------------------------------------------------------------------
    @property
    def parallel(self) -> int:
        """P, the trials that may be out at once (``--parallel``; 1: one at a time)."""
        return int(self.config.parallel)

    def ask(self, worker: str | None = None, *, wait: bool = True, timeout: float | None = None) -> Trial:
        """The next trial to evaluate: raw ``theta`` (shape (D,)), ``W``, ``b``, its episode seeds and source.

        ``worker`` names who evaluates it (a plain name: letters, digits, ``.``, ``_``, ``-``, up to
        64 characters, starting with a letter or digit; None: the unnamed worker). A worker gets its
        own pending trial again until it tells it
        (after a restart too: no LLM call is made twice); another worker gets another trial, up
        to ``--parallel`` P out at once. Past P (or while a round, a phase or a CMA-ES generation
        waits for trials that are out) ``ask`` blocks until a trial is told, up to ``timeout``
        seconds (None: no limit), or with ``wait=False`` raises TrialsOut at once.

        Raises StudyComplete when the budget is spent or the search stopped; TrialsOut (above);
        ConfigError for a worker name that is not a plain name; LLMError when the endpoint stays
        down (the study stays as it was, resumable); StopSearch when the method cannot go on (the
        study is then stopped, with the reason, and can be finalized).
        """
        name = "" if worker is None else check_worker(worker)
        return wait_for(partial(self._ask_once, name), wait=wait, timeout=timeout, out=lambda: len(self.store.pending_trials()))

    def _ask_once(self, name: str) -> Trial | str:
        """The trial for worker ``name``, or why it must wait (one line; ``scheduling``)."""
        with file_lock(self.run_dir, STUDY_LOCK):
            out = self._pending_trials()
            got = held(out, name, self.parallel)
            if got is not None:
                trial, hand = got
                if hand:
                    self.store.assign(trial.number, name)
                return replace(trial, worker=name) if hand else trial
            self._check_stop(told=False)
            check_left(self.store, self.run_dir, self.total, out)
            if len(out) >= self.parallel:
                return f"{len(out)} trials are out, the most at once (--parallel {self.parallel}): {holders(out)}; tell one first"
            queue = self.store.queued()
            before = len(queue)
            trials = propose(self._phases, self.store, self.run_dir, out, worker=name, parallel=self.parallel, task=self.task,
                             episode_seeds=lambda number: tuple(self.streams.episode_seeds(number, self.config.episodes)), queue=queue)
            if isinstance(trials, str):
                return trials
            self.store.add_pending_many(trials, limit=self.parallel, queued=queue if len(queue) != before else None)
            return trials[0]

    def enqueue(self, theta: Sequence[float] | None = None, *, W: Any = None, b: Any = None, note: str = "") -> int:
        """Queue a policy you have (raw ``theta``, shape (D,), or ``W`` (n_s, n_a) and ``b`` (n_a,)
        of ``u = s @ W + b``) as the next new trial asked, in that trial's warm-up or search place
        (``warm_start``); returns its place in the queue (1: next). Raises ConfigError for a policy
        of the wrong shape or values, or when there is no place left for it."""
        from .warm_start import enqueue, init_thetas

        given = {"theta": theta} if W is None and b is None else {"W": W, "b": b}
        if theta is not None and (W is not None or b is not None):
            raise ConfigError("enqueue takes theta, or W and b: not both")
        [raw] = init_thetas([given], self.task, box=self.config.box, warmup=1)
        with file_lock(self.run_dir, STUDY_LOCK):
            return enqueue(self.store, raw, task=self.task, box=self.config.box, search_takes=self.method.phase in ("props_phase", "random_phase"),
                           warmup=self.config.warmup, planned_end=stopping.search_end(self.store) or self._planned_end, note=note)  # fmt: skip

    @overload
    def tell(self, trial: Trial | int, returns: float | Sequence[float] | None = None, *,
             components: Mapping[str, float] | Sequence[Mapping[str, float]] | None = None,
             diagnostics: Mapping[str, float | str] | Sequence[Mapping[str, float | str]] | None = None,
             feedback: Feedback | None = None, eval_s: float | None = None, failed: None = None,
             worker: str | None = None) -> Candidate: ...

    @overload
    def tell(self, trial: Trial | int, returns: None = None, *, components: None = None, diagnostics: None = None,
             feedback: None = None, eval_s: float | None = None, failed: str, worker: str | None = None) -> None: ...

    def tell(self, trial: Trial | int, returns: float | Sequence[float] | None = None, *,
             components: Mapping[str, float] | Sequence[Mapping[str, float]] | None = None,
             diagnostics: Mapping[str, float | str] | Sequence[Mapping[str, float | str]] | None = None,
             feedback: Feedback | None = None, eval_s: float | None = None, failed: str | None = None,
             worker: str | None = None) -> Candidate | None:
        """Tell a pending ``trial`` (or its number) its raw feedback; returns the recorded candidate.

        ``returns`` is one episode's return or one per episode (raw reward units); ``components``
        (each declared reward component's sum over the episode, by name) and ``diagnostics`` (each
        declared diagnostic's value) one mapping, or one per episode. Their mean is the candidate's
        feedback (paper Sec. II-C); encoding happens here. ``feedback`` instead passes an evaluated
        ``Feedback`` (``optimize``). Trials out at once (``--parallel``) are told in any order.

        ``failed="e-stop at 3.2 s"`` instead records that the trial could not be evaluated (returns
        None): it is kept with its reason, never shown to the LLM, never selected, and uses up its
        place in the budget unless ``retry`` asks it again. ``worker`` (default: the worker of a
        ``Trial`` given) must be the worker holding the trial.

        Nothing is stored when this raises ConfigError: a trial that is not pending or was already
        told, one another worker holds, one no worker has been handed yet (the rest of a round, a
        retried trial: ask for it first), an empty ``failed`` reason, a non-finite value, a missing or unknown
        component, an unknown diagnostic, an ``episode_length`` that is not a number of steps, a mismatch
        between the episodes given, or fewer returns than the trial asked episodes for (more are welcome:
        the mean of all is used).
        """
        number = trial if isinstance(trial, int) else trial.number
        teller = worker if worker is not None else (None if isinstance(trial, int) else trial.worker)
        if teller:
            check_worker(teller)
        if failed is not None:
            failed = failure_reason(failed)
        with file_lock(self.run_dir, STUDY_LOCK):
            out = self.store.pending_trials()
            pending = next((t for t in out if t.number == number), None)
            if pending is None:
                raise not_pending(self.store, number, out, run_dir=self.run_dir, total=self.total)
            check_teller(pending, teller, None if isinstance(trial, int) else trial.theta, run_dir=self.run_dir)
            if failed is not None:
                check_failed_alone(number, returns, feedback, components, diagnostics)
                self.store.fail_trial(number, failed)
                self._phases.sync()
                return None
            cand = told_candidate(pending, returns, components, diagnostics, feedback=feedback, eval_s=eval_s, task=self.task,
                                  codec=self.codec)
            self.store.record_trial(cand)
            self._check_stop(told=True)
            self._phases.sync()
            return cand

    def retry(self, trial: Trial | int) -> Trial:
        """Ask a failed trial again: the same parameters and seeds, under its own number, pending
        again for the next worker that asks (its place in the budget is kept). Returns it.
        Raises ConfigError when it did not fail, when the study is finalized (its policy is handed
        over: nothing more is asked), or when ``--parallel`` trials are already out."""
        number = trial if isinstance(trial, int) else trial.number
        with file_lock(self.run_dir, STUDY_LOCK):
            check_retry(self.store, number, self.run_dir, self.parallel)
            again = self.store.retry_trial(number, limit=self.parallel)
            self._phases.sync()
            return again

    @property
    def failed(self) -> list[tuple[Trial, str]]:
        """The failed trials (not asked again), by number, each with its reason."""
        return self.store.failed_trials()

    def _get_phases(self) -> list[Phase]:
        """The run's phases, their proposers told every settled trial (``phases.RunPhases``)."""
        return self._phases.phases()

    # -- the env-driven loop ------------------------------------------------------------------
    def _no_env(self) -> ConfigError:
        """The one line for running the env loop of a task that has no env."""
        return ConfigError(f"task {self.task.name} has no env: drive it with ask/tell ('ppprops ask' / 'ppprops tell')")

    @property
    def evaluator(self) -> Evaluator:
        """The episode runner of the task's env (``config.workers`` processes), made on first use.
        Raises ConfigError for a task without an env."""
        if self._evaluator is None:
            if not self.has_env:
                raise self._no_env()
            self._evaluator = Evaluator(self.task, workers=self.config.workers, env=self._env)
            self._env = None  # the evaluator's now
        return self._evaluator

    def optimize(self, callbacks: Sequence[Callback] = (), events: RunEvents | None = None, *,
                 fleet: Fleet | None = None) -> FinalEval | None:
        """Ask, evaluate on the task's env, tell, until nothing is left to ask; then ``finalize``.

        With ``--parallel`` P > 1 each round's P trials are asked at once (workers ``run-0`` ...
        ``run-{P-1}``) and evaluated side by side by ``fleet`` (an ``evaluation.Fleet``: default
        the study's own ``Evaluator``, whose ``--workers`` processes take the round's episodes;
        ``RayFleet`` for Ray tasks; or your own), then told. With ``--on-episode-error fail-trial``
        a trial whose env raised is told as failed (its error the reason) and the search goes on.

        ``callbacks`` are called after each tell with the told trial (a ``Candidate``) and the
        study; one returning ``False`` stops the search cleanly (status ``stopped: stopped by a
        callback``, then the final evaluation), as Stable-Baselines3's callbacks do. Returns the
        final evaluation (None when ``final_episodes`` is 0).

        Raises:
            LLMError: the endpoint stayed down past the retries (status ``failed``, resumable).
            EpisodeError, PoolError: the user's env raised in reset or step or returned a malformed
                value (``MalformedEnvError``), or the worker processes stopped (status ``failed``,
                resumable once fixed). Any other error is raised as it is, with status ``failed: <it>``.
            KeyboardInterrupt: Ctrl-C (status ``interrupted``, resumable).
            FeedbackKeyError, EpisodeLimitError, WorkerError: the env broke its task's
                declaration (status ``stopped: ...``).
            ConfigError: another process runs this study, or the task has no env.
        """
        from .env_loop import optimize

        if not self.has_env:  # refused before any lock file is made
            raise self._no_env()
        stopping.restart_clock(self.store, self.config.stop, time())
        return optimize(self, callbacks, events if events is not None else self.events, fleet=fleet,
                        fail_trials=self.config.on_episode_error == "fail-trial", pacer=self._phases.pacer(), llm_latency=self._phases.last_latency)

    # -- the result ---------------------------------------------------------------------------
    def finalize(self, returns: Sequence[float] | None = None, *, events: RunEvents | None = None) -> FinalEval | None:
        """Final evaluation of the best trial, then the policy file; the study is then finished
        (or stays ``stopped: <reason>`` when it stopped on purpose).

        With ``returns`` (the user's own final episodes of ``policy()``, raw returns), those are
        stored; otherwise, for a task with an env, the best policy runs on ``final_episodes``
        fresh seeds (``seeding.final_eval_seeds``, never used during the search). A final
        evaluation already stored for the same candidate is kept. Returns it (None when there is
        none). A server kept warm for this study (``ppprops ask``: ``llm.embedded.WarmServer``) is
        stopped. Raises ConfigError before any trial is told or while one is pending, StoreError
        when the policy file cannot be written (the study stays resumable).
        """
        run_episodes = env_final_episodes(lambda: self.evaluator, seed=self.config.seed, episodes=self.config.final_episodes,
                                          events=events if events is not None else self.events)
        best, fe = final_evaluation(self.store, self.run_dir, returns, run_episodes if self.has_env else None)
        write_policy(self.run_dir, self.policy_document(best, fe))
        finish_status(self.store)
        self._phases.stop_warm_server()  # nothing more will be asked
        return fe

    def policy_document(self, best: Candidate | None = None, fe: FinalEval | None = None) -> dict[str, Any]:
        """The policy file's content for ``best`` (default: the candidate to hand over, ``best``)."""
        from .policy_file import policy_document

        best = best if best is not None else self.best
        if best is None:
            raise ConfigError("no trial has been told: there is no policy yet")
        search, final = provenance(self.store, best, fe, method=self.config.method, seed=self.config.seed)
        env = None if self.task.discrete or not self.has_env else self.evaluator.env
        return policy_document(self.task, best.params, env=env, search=search, final_eval=final)

    def policy(self) -> Policy:
        """The deployable policy of the best told trial (raw observation -> action), as the policy file holds it."""
        from .policy_file import Policy

        return Policy(self.policy_document(), np.asarray(self.best.params if self.best is not None else [], dtype=np.float64))


def _phase_settings(config: RunConfig, has_env: bool) -> PhaseSettings:
    """What a run's phases depend on of its config (``phases.PhaseSettings``)."""
    return PhaseSettings(warmup=config.warmup, iterations=config.iterations, selection=config.selection(has_env), box=config.box,
                         mechanisms=config.mechanisms, form=config.form, form_chosen=config.prompt_form == config.form,
                         prompt_settings=config.prompt_settings, llm=config.llm,
                         method_options=config.method_options, on_llm_failure=config.on_llm_failure,
                         parse_retries=config.parse_retries, parallel=int(config.parallel), init_thetas=config.init_thetas)  # fmt: skip


__all__ = ["Study", "StudyComplete", "Trial", "TrialsOut", "check_worker"]
