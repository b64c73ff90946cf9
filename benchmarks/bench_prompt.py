"""1. Prompt compactness: characters and tokens of the final Ant-Ultra prompt in each prompt form.

The history is real: Ant-Ultra (D=88) policies sampled and evaluated by a pp run with a fresh
key, as many as the paper's final prompt held (59 candidates before the 50th call; the run has
no selection stage, so the history holds exactly those 59 and no candidate twice). The prompt that
would be sent next is built by ``ppprops.wire`` in the document form (the embedded model's
default) and in the paper's chat form, in each number format (``wire.forms.NUMBER_FORMATS``),
with K=10 and unbounded (and, for comparison, the chat form with ProPS ``params[i]: v`` pairs),
and counted in characters, in tokens of the embedded model's tokenizer (``_gemma``: llama.cpp's
algorithm on the GGUF's own vocabulary, so no model starts; it gives llama.cpp ``/tokenize``'s
counts exactly) and in tokens of two cloud tokenizers (tiktoken's o200k and cl100k, read offline from the BPE
files of the ``bpe-openai`` package: the ``bench`` extra). The answer's tokens per parameter are
counted on the answer the form's grammar would hold if the model wrote the best shown policy
again (its printed values, in the form's answer frame).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

from _common import Context, Section, cloud_tokenizers, config, pct_less, prompt_after, run_search, table
from _gemma import gemma_tokenizer

from ppprops.wire import numbers

TASK = "Ant-Ultra"
PAPER_K10_CHARS = 22_000  # the paper's final prompt, D=88, K=10 (ProPS form, gpt-oss-20b)
TARGET_TOKENS = 4_000  # the final Ant-Ultra K=10 prompt, in Gemma tokens, in every form
HISTORY_MARK = "5. Here is the history:\n"
# (key, prompt form, parameter style, number format, label); decimal is the default format, grid the opt-in one
VARIANTS: tuple[tuple[str, str, str, str, str], ...] = (
    ("document-decimal", "document", "list", "decimal", "document, decimal (default)"),
    ("document", "document", "list", "grid", "document, grid (--number-format grid)"),
    ("document-rows", "document", "list", "grid-rows", "document, grid, one label per row (off until benchmark 11)"),
    ("list-decimal", "chat", "list", "decimal", "chat, decimal (default)"),
    ("list", "chat", "list", "grid", "chat, grid (--number-format grid)"),
    ("indexed", "chat", "indexed", "decimal", "chat, ProPS `params[i]: v`, decimal"),
)
UNBOUNDED = ("document", "list")  # the variants also shown with the whole history (K=all)
ROWS = replace(numbers.GRID, name="grid-rows", row_labels=True)  # the grid with one label per row of W (wire.numbers)


def history_part(prompt: str, form: str) -> str:
    if form == "document":
        return prompt.split("\n\n", 1)[1]  # everything after the one-line header, the open block included
    return prompt.split(HISTORY_MARK, 1)[1]


def best_answer(prompt: str, form: str) -> str:
    """What the form's answer holds if the model writes the best shown policy again: the document
    form's continuation (the last complete entry's list after ``[``, closing bracket included), or
    the chat form's ``{"params": [...]}`` with the last entry's printed values."""
    if form == "document":
        last = prompt.rsplit("params: [", 2)[-2]  # the best entry's list (the open block is the last "params: [")
        return last.split("]", 1)[0] + "]"
    hist = history_part(prompt, form)
    lines = [ln for ln in hist.splitlines() if ln.startswith("params: [")]
    values = lines[-1].removeprefix("params: [").removesuffix("]")
    return '{"params": [' + values.replace(",", ", ") + "]}"


def counts(gemma: Any, cloud: dict[str, Any], text: str) -> dict[str, int]:
    return {"chars": len(text), "gemma": gemma.count(text), **{k: len(enc.encode(text)) for k, enc in cloud.items()}}


def run(ctx: Context) -> Section:
    numbers.NUMBER_FORMATS[ROWS.name] = ROWS
    try:
        return _run(ctx)
    finally:
        numbers.NUMBER_FORMATS.pop(ROWS.name, None)


def _run(ctx: Context) -> Section:
    entries = 12 if ctx.quick else 59
    # select_top=0: no selection stage, so the history is the search's own 59 candidates
    run_dir = run_search(config(TASK, warmup=entries, iterations=0, seed=0, select_top=0), ctx.dir("prompt") / "ant-history")
    D = 88
    cloud = cloud_tokenizers()
    client = gemma_tokenizer()
    rows, data = [], {}
    for k in (10, 0):
            for key, form, style, fmt, label in VARIANTS:
                if k == 0 and key not in UNBOUNDED:
                    continue
                over: dict[str, Any] = {"params_style": style, "number_format": fmt}
                text = prompt_after(run_dir, top_k=k, form=form, **over)
                hist = history_part(text, form)
                n = min(k, entries) if k else entries
                whole, h = counts(client, cloud, text), counts(client, cloud, hist)
                ans = counts(client, cloud, best_answer(text, form)) if style == "list" else None
                item: dict[str, Any] = {"entries": n, **whole, "history": h, "history_gemma_per_param": h["gemma"] / (n * D),
                                        "history_chars_per_param": h["chars"] / (n * D)}
                if ans:
                    item["answer_gemma_per_param"] = ans["gemma"] / D
                    item["answer_o200k_per_param"] = ans["o200k"] / D
                data[f"K{k}_{key}"] = item
                rows.append([f"K={k or 'all'}", label, n, f"{whole['chars']:,}", f"{whole['gemma']:,}", f"{whole['o200k']:,}",
                             f"{whole['cl100k']:,}", f"{h['gemma'] / (n * D):.2f}",
                             f"{ans['gemma'] / D:.2f} / {ans['o200k'] / D:.2f}" if ans else "-"])
    k10 = {key: data[f"K10_{key}"] for key, *_ in VARIANTS}
    doc, chat = k10["document"], k10["list"]
    met = doc["gemma"] <= TARGET_TOKENS and chat["gemma"] <= TARGET_TOKENS
    before = {"document": k10["document-decimal"], "chat": k10["list-decimal"]}
    data["target_tokens"], data["met"] = TARGET_TOKENS, met
    fixed = chat["gemma"] - chat["history"]["gemma"]
    body = [
        f"Final prompt after {entries} evaluated Ant-Ultra policies (D={D}, pp preset), built by the prompt builder "
        "from a real run's encoded history (no selection stage: each candidate once); tokens: the embedded Gemma 3 270M "
        "tokenizer's (llama.cpp's algorithm on the GGUF's vocabulary, benchmarks/_gemma.py; on the six prompts of the decimal "
        "format's table measured before the grid it gave llama.cpp /tokenize's counts exactly) and the cloud tokenizers o200k "
        "and cl100k (tiktoken, BPE files of `bpe-openai`). "
        "Answer tokens per parameter: the best shown policy written again in the form's answer frame (Gemma / o200k).",
        "",
        table(["history", "prompt form", "entries shown", "prompt chars", "Gemma tokens", "o200k", "cl100k",
               "history Gemma tokens/param", "answer tokens/param (Gemma / o200k)"], rows),
        "",
        f"- K=10, document form with --number-format grid: **{doc['gemma']:,} Gemma tokens** ({doc['chars']:,} chars, "
        f"{pct_less(doc['chars'], PAPER_K10_CHARS):.1f}% fewer characters than the paper's {PAPER_K10_CHARS:,}).",
        f"- K=10, chat form with the grid: **{chat['gemma']:,} Gemma tokens** ({chat['o200k']:,} o200k); its fixed sections and feedback "
        f"lines take {fixed:,} Gemma tokens.",
        f"- Against the decimal format (the default): document {before['document']['gemma']:,} -> "
        f"{doc['gemma']:,} Gemma tokens ({pct_less(doc['gemma'], before['document']['gemma']):.0f}% fewer), chat "
        f"{before['chat']['gemma']:,} -> {chat['gemma']:,} ({pct_less(chat['gemma'], before['chat']['gemma']):.0f}% fewer); "
        f"o200k document {before['document']['o200k']:,} -> {doc['o200k']:,}, chat {before['chat']['o200k']:,} -> {chat['o200k']:,}.",
        f"- Target at most {TARGET_TOKENS:,} Gemma tokens in every form (K=10): {'met' if met else 'NOT met'}. With one label "
        f"per row of W the document form would take {k10['document-rows']['gemma']:,} (not the default: benchmark 11 has not "
        "yet shown that the model keeps its place with it).",
    ]
    ctx.cache["prompt_data"] = data
    quality = ctx.cache.get("quality_forms")
    if quality:
        body += ["- Search results of the two prompt forms at an equal budget (embedded model; from benchmark 6):", "",
                 table(["task", "prompt form", "seeds", "best return", "final-evaluation return", "median"], quality)]
    targets = [(f"final prompt, D=88, K=10 <= {TARGET_TOKENS:,} Gemma tokens in every form",
                f"document {doc['gemma']:,}, chat {chat['gemma']:,} (o200k {doc['o200k']:,} / {chat['o200k']:,})", met)]
    for d, c in zip(quality[::2], quality[1::2]) if quality else ():  # rows: document, then chat, per task
        targets.append((f"search results of the document form no worse than the chat form ({d[0]}, final evaluation)",
                        f"{d[4]} vs {c[4]}; median {d[5]} vs {c[5]} ({d[2]} vs {c[2]} seeds)", None))
    return Section("prompt", "1. Prompt compactness", "\n".join(body), data, targets=targets)
