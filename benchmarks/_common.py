"""Shared pieces of the benchmark suite: the machine, runs, prompt replay, the embedded server.

Each benchmark module exposes ``run(ctx) -> Section``; ``run_all.py`` calls them in one process
and writes ``RESULTS.md`` from their sections, so every figure in it comes from one run.
"""

from __future__ import annotations

import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from ppprops import __version__
from ppprops.client.context import prompt_context
from ppprops.client.hardening import codec_for
from ppprops.client.secrets import Secrets
from ppprops.config import LLMConfig, RunConfig
from ppprops.llm.client import EndpointClient
from ppprops.methods import resolve
from ppprops.proposers.llm import LLMProposer, LLMSearch
from ppprops.rundir import policy_path
from ppprops.runner import load_run, start
from ppprops.seeding import Streams
from ppprops.store import Candidate, open_store
from ppprops.wire.document import document_temperature
from ppprops.wire.forms import CHAT, CHAT_TEMPERATURE, DOCUMENT, FORMS, FormRequest, answer_budget, params_grammar, params_schema

ROOT = Path(__file__).resolve().parent.parent


@dataclass
class Section:
    """One benchmark's part of RESULTS.md: Markdown for people, ``data`` for results.json."""

    key: str
    title: str
    body: str
    data: dict[str, Any] = field(default_factory=dict)
    seconds: float = 0.0
    targets: list[tuple[str, str, bool | None]] = field(default_factory=list)  # (target, measured, met; None: no target)


# --quick: every search a benchmark starts in this process (``config``) asks for at most this many
# answer tokens and makes no corrections, so an LLM iteration costs one prefill and a few tokens:
# the answers are cut off and the candidates are fallbacks, which exercises the same code paths
# (requests, store, replay, timings) without the minutes a D=782 answer takes on 2 cores.
QUICK_MAX_TOKENS = 8
_quick = False


@dataclass
class Context:
    out: Path  # working directory for runs; kept so every figure can be traced to a store
    quick: bool = False  # tiny budgets: checks the suite end to end, figures mean nothing
    keep: bool = False  # reuse a grid already recorded under ``out`` (resume it) instead of starting afresh
    collect: bool = False  # with keep: start nothing, report the runs the grid has finished (it may run elsewhere)
    cache: dict[str, Any] = field(default_factory=dict)  # runs one benchmark leaves for another

    def __post_init__(self) -> None:
        global _quick
        _quick = self.quick  # config() reads it: the suite runs one Context per process

    def dir(self, name: str) -> Path:
        d = self.out / name
        d.mkdir(parents=True, exist_ok=True)
        return d


def commit() -> str:
    """The short git commit of the code measured, ``+changes`` when the work tree differs from it ("" outside git)."""
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                              timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT, capture_output=True,
                               text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""
    return head + ("+changes" if head and dirty else "")


def machine() -> str:
    """CPU model, cores, memory, OS, Python and the code's commit: enough to compare two RESULTS.md."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem = ""
    try:
        kb = int(Path("/proc/meminfo").read_text().split("MemTotal:")[1].split()[0])
        mem = f", {kb / 2**20:.0f} GiB RAM"
    except (OSError, IndexError, ValueError):
        pass
    code = commit()
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return (f"{cpu}, {os.cpu_count()} logical CPUs{mem}, {platform.system()} {platform.release()}, "
            f"Python {platform.python_version()}, ppprops {__version__}{f' ({code})' if code else ''}, "
            f"load average at start {load:.2f}")


def config(task: str, method: str = "pp", **kw: Any) -> RunConfig:
    """A benchmark run's settings; under ``--quick`` with ``QUICK_MAX_TOKENS`` and no corrections."""
    llm = kw.pop("llm", LLMConfig())
    base: dict[str, Any] = dict(warmup=10, iterations=10, top_k=10, final_episodes=0, seed=0)
    base.update(kw)
    if _quick:
        llm = replace(llm, max_tokens=llm.max_tokens or QUICK_MAX_TOKENS)
        base["parse_retries"] = 0
    return RunConfig(task=task, method=method, mechanisms=resolve(method), llm=llm, **base)


def run_search(cfg: RunConfig, run_dir: Path, secrets: Secrets | None = None) -> Path:
    """A real search, started fresh (a leftover directory from an earlier suite run is replaced).
    Passing another run's ``secrets`` gives both runs the same encoding, hence the same warm-up history."""
    if run_dir.exists():
        shutil.rmtree(run_dir)
    start(cfg, run_dir, secrets=secrets)
    return run_dir


def grid_dir(ctx: Context, name: str, spec: Path) -> tuple[Path, list[str], bool]:
    """A benchmark's ``ppprops experiment`` grid under ``ctx.out/name``: deleted first unless
    ``--keep``; with ``--collect`` it must exist. Returns (its directory, the command that runs
    ``spec`` there, whether a recorded grid is reused)."""
    out = ctx.out / name
    reused = ctx.keep and (out / "grid.json").exists()
    if out.exists() and not ctx.keep:
        shutil.rmtree(out)
    if ctx.collect and not reused:
        raise SystemExit(f"--collect reports a recorded grid, and {out} holds none (run with --keep, or without both)")
    return out, [sys.executable, "-m", "ppprops", "experiment", str(spec), "--out", str(out), "--quiet"], reused


def finished(run_dir: Path) -> bool:
    """Whether a recorded run finished: its policy file is written after the final evaluation
    (the rule ``privacy.matrix.run_matrix`` keeps finished runs by)."""
    return policy_path(run_dir).exists()


def run_secrets(run_dir: Path) -> Secrets:
    store, _, secrets = load_run(run_dir)
    store.close()
    return secrets


def llm_calls(run_dir: Path) -> list[dict[str, Any]]:
    store = open_store(run_dir)
    try:
        return store.llm_calls()
    finally:
        store.close()


def timings(response: str | None) -> dict[str, float]:
    """llama.cpp's own accounting of one answer: cache_n (prompt tokens reused from its cache),
    prompt_n (prompt tokens it processed), prompt_ms, predicted_n, predicted_ms."""
    if not response:
        return {}
    try:
        t = json.loads(response).get("timings") or {}
    except (ValueError, AttributeError):
        return {}
    return {k: float(v) for k, v in t.items() if isinstance(v, (int, float))}


def _proposer(run_dir: Path, top_k: int | None = None, form: str = "chat", **overrides: Any) -> tuple[LLMProposer, list[Candidate]]:
    """A ProPS proposer rebuilt from a recorded run's store and key (told nothing yet), and the
    run's candidates. ``top_k``, ``form`` (chat or document) and ``overrides`` change its history
    bound, prompt form and prompt context."""
    store, cfg, secrets = load_run(run_dir)
    try:
        cands = store.candidates()
    finally:
        store.close()
    if "number_format" in overrides:  # the codec follows the format (the grid's factor), not only the printing
        fmt = overrides["number_format"]  # a benchmark's variant of the grid ("grid-...") keeps the grid's codec
        cfg = replace(cfg, number_format="grid" if fmt.startswith("grid") else fmt)
    task = cfg.make_task()
    codec = codec_for(secrets, task, cfg.encoding)
    k = cfg.top_k if top_k is None else top_k
    ctx = replace(prompt_context(task, cfg.prompt_settings(form), codec), history_limit=k, **{"param_digits": cfg.digits(form), **overrides})
    run = LLMSearch(llm=None, codec=codec, context=ctx, top_k=k, box=cfg.box, streams=Streams(cfg.seed))  # type: ignore[arg-type]
    return LLMProposer(run, form=FORMS[form]), cands


def replay_prompts(run_dir: Path, form: str = "chat", **overrides: Any) -> list[tuple[int, str]]:
    """(iteration, prompt) for every LLM iteration of a recorded ProPS run, rebuilt with the
    prompt context changed by ``overrides`` (e.g. ``layout="history-first"``). With no overrides
    the result must equal what the run sent; the caller can check that."""
    prop, cands = _proposer(run_dir, form=form, **overrides)
    out = []
    for c in cands:
        if c.source in ("llm", "fallback"):
            out.append((c.iteration, prop.prompt()))
        prop.tell(c)
    return out


def replay_requests(run_dir: Path, form: str = "chat", **overrides: Any) -> list[tuple[int, str, str | None]]:
    """As ``replay_prompts``, with the continuation grammar of each document-form request (None for chat)."""
    prop, cands = _proposer(run_dir, form=form, **overrides)
    out = []
    for c in cands:
        if c.source in ("llm", "fallback"):
            out.append((c.iteration, prop.prompt(), prop.grammar() if form == "document" else None))
        prop.tell(c)
    return out


def run_form(run_dir: Path) -> str:
    """The prompt form a recorded run used: chat or document."""
    store, cfg, _ = load_run(run_dir)
    store.close()
    return cfg.form


def prompt_after(run_dir: Path, *, top_k: int, form: str = "chat", **overrides: Any) -> str:
    """The prompt the run would send next, after all its recorded candidates, with K = ``top_k``."""
    prop, cands = _proposer(run_dir, top_k, form, **overrides)
    for c in cands:
        prop.tell(c)
    return prop.prompt()


def sent_prompts(run_dir: Path) -> list[tuple[int, str]]:
    """(iteration, prompt) of every first attempt the run actually sent, in either prompt form."""
    out = []
    for c in llm_calls(run_dir):
        if c["attempt"] == 0 and c["retry"] == 0:
            body = json.loads(c["request"])
            out.append((c["iteration"], body["prompt"] if "prompt" in body else body["messages"][0]["content"]))
    return out


@contextmanager
def embedded(context_size: int = 32768) -> Iterator[EndpointClient]:
    """A fresh embedded server (empty prompt cache) and a client for it."""
    client = EndpointClient(LLMConfig(context_size=context_size)).start()
    try:
        yield client
    finally:
        client.close()


def request_for(form: str, text: str, D: int, iteration: int = 0, grammar: str | None = None) -> FormRequest:
    """The request a prompt form sends for a prompt ``text`` it wrote (the first attempt, default
    temperature), for replaying a recorded prompt."""
    if form == DOCUMENT.name:
        return FormRequest(DOCUMENT.name, DOCUMENT.endpoint, D, iteration, prompt=text, sampling={"temperature": document_temperature(0, 0)},
                           answer_tokens=answer_budget(D, labels=True), grammar=grammar, stop=("]",))
    return FormRequest(CHAT.name, CHAT.endpoint, D, iteration, messages=({"role": "user", "content": text},),
                       sampling={"temperature": CHAT_TEMPERATURE}, answer_tokens=answer_budget(D), explains=True,
                       json_schema=params_schema(D), grammar=params_grammar(D))


def count_tokens(client: EndpointClient, text: str) -> int:
    """Tokens of ``text`` under the embedded model's own tokenizer (llama.cpp /tokenize)."""
    root = client.base_url.rstrip("/").removesuffix("/v1")
    req = urllib.request.Request(root + "/tokenize", data=json.dumps({"content": text}).encode(),
                                 headers={"Content-Type": "application/json"}, method="POST")
    with urllib.request.urlopen(req, timeout=120) as resp:
        return len(json.loads(resp.read())["tokens"])


# The cloud tokenizers: tiktoken's encodings, read from the BPE files the ``bpe-openai`` package ships
# (the ``bench`` extra); their SHA-256 equal the ones tiktoken checks, so nothing is downloaded.
CLOUD_ENCODINGS = {"o200k": ("o200k_base", "https://openaipublic.blob.core.windows.net/encodings/o200k_base.tiktoken"),
                   "cl100k": ("cl100k_base", "https://openaipublic.blob.core.windows.net/encodings/cl100k_base.tiktoken")}


def cloud_tokenizers() -> dict[str, Any]:
    """``{"o200k": Encoding, "cl100k": Encoding}``: tiktoken's encodings loaded offline from the BPE
    files of the ``bpe-openai`` package (placed in a private tiktoken cache under the names tiktoken
    looks for; tiktoken still checks each file's SHA-256). Raises SystemExit naming the ``bench`` extra
    when either package is missing."""
    import gzip
    import hashlib
    import tempfile
    from importlib import resources

    try:
        import tiktoken
        import tiktoken.load
    except ImportError:
        raise SystemExit("counting cloud tokens needs tiktoken and bpe-openai: pip install -e '.[bench]'") from None
    try:
        data = resources.files("bpe_openai").joinpath("data")
    except ModuleNotFoundError:
        raise SystemExit("counting cloud tokens needs the bpe-openai package: pip install -e '.[bench]'") from None
    cache = Path(tempfile.mkdtemp(prefix="ppprops-tiktoken-"))
    for name, url in CLOUD_ENCODINGS.values():
        raw = gzip.decompress(data.joinpath(f"{name}.tiktoken.gz").read_bytes())
        (cache / hashlib.sha1(url.encode()).hexdigest()).write_bytes(raw)
    before = os.environ.get("TIKTOKEN_CACHE_DIR")
    os.environ["TIKTOKEN_CACHE_DIR"] = str(cache)
    try:
        return {key: tiktoken.get_encoding(name) for key, (name, _) in CLOUD_ENCODINGS.items()}
    finally:
        if before is None:
            os.environ.pop("TIKTOKEN_CACHE_DIR", None)
        else:
            os.environ["TIKTOKEN_CACHE_DIR"] = before
        shutil.rmtree(cache, ignore_errors=True)


def mean_std(values: Sequence[float]) -> str:
    """``mean (std)`` as the paper's tables print it; population std over seeds."""
    if not values:
        return "n/a"
    return f"{statistics.fmean(values):.1f} ({statistics.pstdev(values):.1f})"


def table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def pct_less(new: float, old: float) -> float:
    """How much smaller ``new`` is than ``old``, in percent (the paper's "-80.2%")."""
    return 100.0 * (1.0 - new / old) if old else float("nan")


@contextmanager
def stopwatch() -> Iterator[list[float]]:
    box = [0.0]
    t0 = time.perf_counter()
    try:
        yield box
    finally:
        box[0] = time.perf_counter() - t0
