"""1. Prompt compactness: characters and tokens of the final Ant-Ultra prompt in each prompt form.

The history is real: Ant-Ultra (D=88) policies sampled and evaluated by a pp run with a fresh
key, as many as the paper's final prompt held (10 warm-up + 49 LLM candidates before the 50th
call). The prompt that would be sent next is built by ``ppprops.wire`` in the document form (the
embedded model's default), in the paper's chat form with the list parameter form (the default
for other endpoints) and with ProPS ``params[i]: v`` pairs, with K=10 and unbounded, and counted
in characters and in tokens of the embedded model's tokenizer. Search results of the document
and chat forms at an equal budget come from the quality benchmark.
"""

from __future__ import annotations

from _common import Context, Section, config, count_tokens, embedded, pct_less, prompt_after, run_search, table

TASK = "Ant-Ultra"
PAPER_K10_CHARS = 22_000  # the paper's final prompt, D=88, K=10 (ProPS form, gpt-oss-20b)
PAPER_FULL_CHARS = 114_000  # the same with the whole history
TARGET_CHARS = 8_000  # the final Ant-Ultra K=10 prompt, in characters
HISTORY_MARK = "5. Here is the history:\n"
# (key, prompt form, parameter style, label)
FORMS = (("document", "document", "list", "document (embedded default)"), ("list", "chat", "list", "chat, list (default elsewhere)"),
         ("indexed", "chat", "indexed", "chat, ProPS `params[i]: v`"))


def history_part(prompt: str, form: str) -> str:
    if form == "document":
        return prompt.split("\n\n", 1)[1]  # everything after the one-line header, the open block included
    return prompt.split(HISTORY_MARK, 1)[1]


def run(ctx: Context) -> Section:
    entries = 12 if ctx.quick else 59
    run_dir = run_search(config(TASK, warmup=entries, iterations=0, seed=0), ctx.dir("prompt") / "ant-history")
    D = 88
    rows, data = [], {}
    with embedded() as client:
        for k in (10, 0):
            for key, form, style, label in FORMS:
                text = prompt_after(run_dir, top_k=k, form=form, params_style=style)
                hist = history_part(text, form)
                n = min(k, entries) if k else entries
                chars, toks = len(text), count_tokens(client, text)
                h_chars, h_toks = len(hist), count_tokens(client, hist)
                data[f"K{k}_{key}"] = {"entries": n, "chars": chars, "tokens": toks, "history_chars": h_chars,
                                       "history_chars_per_param": h_chars / (n * D),
                                       "history_tokens_per_param": h_toks / (n * D)}
                rows.append([f"K={k or 'all'}", label, n, f"{chars:,}", f"{toks:,}", f"{h_chars / (n * D):.2f}",
                             f"{h_toks / (n * D):.2f}"])
    doc, ours, props = data["K10_document"], data["K10_list"], data["K10_indexed"]
    data["target_chars"] = TARGET_CHARS
    data["met"] = doc["chars"] <= TARGET_CHARS
    fixed = ours["chars"] - ours["history_chars"]
    body = [
        f"Final prompt after {entries} evaluated Ant-Ultra policies (D={D}, pp preset, 2 decimals), built by the prompt builder "
        "from a real run's encoded history; tokens are the embedded Gemma 3 270M tokenizer's.",
        "",
        table(["history", "prompt form", "entries shown", "prompt chars", "prompt tokens", "history chars/param",
               "history tokens/param"], rows),
        "",
        f"- K=10, document form (what the embedded model is sent): **{doc['chars']:,} characters** ({doc['tokens']:,} tokens) "
        f"against the paper's {PAPER_K10_CHARS:,} ({pct_less(doc['chars'], PAPER_K10_CHARS):.1f}% less; target at most "
        f"{TARGET_CHARS:,}: {'met' if data['met'] else 'NOT met'}). It has no fixed sections: a one-line header, the entries "
        "and the open block.",
        f"- K=10, chat form (the paper's prompt, kept for capable endpoints): {ours['chars']:,} characters with the list form, "
        f"{props['chars']:,} with ProPS pairs. Its fixed sections (task description, parameters, feedback, interaction) take "
        f"{fixed:,} characters, {100 * fixed / ours['chars']:.0f}% of it; they carry the task description a capable model "
        "uses, so they stay, and the chat form stays above 8,000 characters.",
        f"- The list form against ProPS pairs with the same numbers: {pct_less(ours['chars'], props['chars']):.1f}% fewer characters, "
        f"{pct_less(ours['tokens'], props['tokens']):.1f}% fewer tokens "
        f"({ours['history_tokens_per_param']:.2f} against {props['history_tokens_per_param']:.2f} tokens per parameter).",
    ]
    ctx.cache["prompt_data"] = data
    quality = ctx.cache.get("quality_forms")
    if quality:
        body += ["- Search results of the two prompt forms at an equal budget (embedded model; from benchmark 6):", "",
                 table(["task", "prompt form", "seeds", "best return", "final-evaluation return", "median"], quality)]
    targets = [(f"final prompt, D=88, K=10 <= {TARGET_CHARS:,} chars (document form, the embedded default)",
                f"{doc['chars']:,} chars (chat form: {ours['chars']:,})", data["met"])]
    for d, c in zip(quality[::2], quality[1::2]) if quality else ():  # rows: document, then chat, per task
        targets.append((f"search results of the document form no worse than the chat form ({d[0]}, final evaluation)",
                        f"{d[4]} vs {c[4]}; median {d[5]} vs {c[5]} ({d[2]} vs {c[2]} seeds)", None))
    return Section("prompt", "1. Prompt compactness", "\n".join(body), data, targets=targets)
