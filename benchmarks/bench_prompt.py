"""1. Prompt compactness: characters and tokens per parameter, our list form against ProPS pairs.

The history is real: Ant-Ultra (D=88) policies sampled and evaluated by a pp run with a fresh
key, as many as the paper's final prompt held (10 warm-up + 49 LLM candidates before the 50th
call). The prompt that would be sent next is built by ``ppprops.wire`` in both parameter forms,
with K=10 and unbounded, and counted in characters and in tokens of the embedded model's
tokenizer. Search results of the two forms at an equal budget come from the quality benchmark.
"""

from __future__ import annotations

from _common import Context, Section, config, count_tokens, embedded, pct_less, prompt_after, run_search, table

TASK = "Ant-Ultra"
PAPER_K10_CHARS = 22_000  # the paper's final prompt, D=88, K=10 (ProPS form, gpt-oss-20b)
PAPER_FULL_CHARS = 114_000  # the same with the whole history
HISTORY_MARK = "5. Here is the history:\n"


def history_part(prompt: str) -> str:
    return prompt.split(HISTORY_MARK, 1)[1]


def run(ctx: Context) -> Section:
    entries = 12 if ctx.quick else 59
    run_dir = run_search(config(TASK, warmup=entries, iterations=0, seed=0), ctx.dir("prompt") / "ant-history")
    D = 88
    rows, data = [], {}
    with embedded() as client:
        for k in (10, 0):
            for style in ("list", "indexed"):
                text = prompt_after(run_dir, top_k=k, params_style=style)
                hist = history_part(text)
                n = min(k, entries) if k else entries
                chars, toks = len(text), count_tokens(client, text)
                h_chars, h_toks = len(hist), count_tokens(client, hist)
                data[f"K{k}_{style}"] = {"entries": n, "chars": chars, "tokens": toks, "history_chars": h_chars,
                                         "history_chars_per_param": h_chars / (n * D),
                                         "history_tokens_per_param": h_toks / (n * D)}
                rows.append([f"K={k or 'all'}", "list (default)" if style == "list" else "ProPS `params[i]: v`", n, f"{chars:,}",
                             f"{toks:,}", f"{h_chars / (n * D):.2f}", f"{h_toks / (n * D):.2f}"])
    ours, props = data["K10_list"], data["K10_indexed"]
    data["target_chars"] = PAPER_K10_CHARS / 2
    data["met"] = ours["chars"] <= PAPER_K10_CHARS / 2
    body = [
        f"Final prompt after {entries} evaluated Ant-Ultra policies (D={D}, pp preset, 2 decimals), built by the prompt builder "
        "from a real run's encoded history; tokens are the embedded Gemma 3 270M tokenizer's.",
        "",
        table(["history", "parameter form", "entries shown", "prompt chars", "prompt tokens", "history chars/param",
               "history tokens/param"], rows),
        "",
        f"- K=10, list form: **{ours['chars']:,} characters** against the paper's {PAPER_K10_CHARS:,} "
        f"({pct_less(ours['chars'], PAPER_K10_CHARS):.1f}% less; target at most {PAPER_K10_CHARS // 2:,}: "
        f"{'met' if data['met'] else 'NOT met'}).",
        f"- Against the ProPS form with the same numbers: {pct_less(ours['chars'], props['chars']):.1f}% fewer characters, "
        f"{pct_less(ours['tokens'], props['tokens']):.1f}% fewer tokens "
        f"({ours['history_tokens_per_param']:.2f} against {props['history_tokens_per_param']:.2f} tokens per parameter).",
    ]
    if not data["met"]:
        fixed = ours["chars"] - data["K10_list"]["history_chars"]
        body.append(f"- What limits it: the fixed sections (task description, parameters, feedback, interaction) take {fixed:,} "
                    f"characters, {100 * fixed / ours['chars']:.0f}% of the prompt. The history itself is "
                    f"{data['K10_list']['history_chars']:,} characters, {pct_less(ours['history_chars'], props['history_chars']):.1f}% "
                    "less than in the ProPS form.")
    ctx.cache["prompt_data"] = data
    quality = ctx.cache.get("quality_forms")
    if quality:
        body += ["- Search results of the two forms at an equal budget (CartPole, embedded model; from benchmark 6):", "",
                 table(["parameter form", "best return", "final-evaluation return"], quality)]
    targets = [("final prompt, D=88, K=10 <= 11,000 chars (half the paper's)", f"{ours['chars']:,} chars", data["met"])]
    if quality:
        targets.append(("search results no worse than the ProPS form (CartPole, 5 seeds)",
                        f"best {quality[0][1]} vs {quality[1][1]}; final {quality[0][2]} vs {quality[1][2]}", None))
    return Section("prompt", "1. Prompt compactness", "\n".join(body), data, targets=targets)
