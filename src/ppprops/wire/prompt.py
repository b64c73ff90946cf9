"""Pure functions from (public context, encoded history) to prompt text. Templates live in files."""

from __future__ import annotations

from collections.abc import Sequence
from functools import cache
from importlib import resources
from string import Template

from . import layout
from .encoded import EncodedEntry, PromptContext
from .numbers import fmt, fmt_value, fmt_vector


@cache
def template(name: str) -> Template:
    """The prompt template ``wire/templates/<name>.txt`` (read once); FileNotFoundError for an unknown name."""
    text = resources.files("ppprops.wire.templates").joinpath(f"{name}.txt").read_text(encoding="utf-8")
    return Template(text.rstrip("\n"))


def render(name: str, **values: object) -> str:
    """Template ``name`` (a file in ``wire/templates``) with ``values`` substituted; KeyError if one is missing."""
    return template(name).substitute(**values)


TERSE = ("feedback_detailed", "feedback_scalar", "interaction", "scale_note")  # templates with a ``*_terse`` wording


def wording(ctx: PromptContext, name: str) -> str:
    """The template of ``name`` in the context's number format: its ``*_terse`` wording in a terse
    format (the grid, ``wire.numbers.NumberFormat.terse``) where one exists, else ``name``."""
    return f"{name}_terse" if ctx.numbers.terse and name in TERSE else name



def task_section(ctx: PromptContext) -> str:
    """The task description (ProPS+), or with ``describe_task`` off only the policy's structure (ProPS)."""
    action_rule = render("action_discrete" if ctx.discrete else "action_continuous")
    if not ctx.describe_task:
        return render("task_withheld", n_s=ctx.n_s, n_a=ctx.n_a, action_rule=action_rule)
    obs = "\n".join(f"- s[{i}] {name}: {meaning}" for i, (name, meaning) in enumerate(ctx.observations))
    acts = "\n".join(f"- u[{j}]: {meaning}" for j, meaning in enumerate(ctx.actions))
    return render(
        "task",
        summary=ctx.summary,
        n_s=ctx.n_s,
        n_a=ctx.n_a,
        observations=obs,
        actions=acts,
        action_rule=action_rule,
        reward_text=ctx.reward_text,
        hints=ctx.hints,
    ).rstrip()


_PARAM_TEMPLATES = {"scale": "parameters_encoded", "affine": "parameters_offset", "warp": "parameters_warped"}
_REWARD_NOTES = {"scale": "scale_note", "affine": "scale_note_offset", "warp": "scale_note_warped"}


def mlp_structure(ctx: PromptContext) -> str:
    """An MLP's structure in words (``policy_mlp``): its layers, activation, output and flat layout."""
    sizes = ctx.sizes
    steps, prev = [], "s"
    for number, o in enumerate(sizes[1:-1], start=1):
        steps.append(f"h{number}[j] = {ctx.activation}(sum_i {prev}[i]*W{number}[i][j] + b{number}[j]) for its {o} hidden units")
        prev = f"h{number}"
    L = len(sizes) - 1
    steps.append(f"the output u[j] = sum_i {prev}[i]*W{L}[i][j] + b{L}[j]")
    return render("policy_mlp", n_layers=L, forward="; ".join(steps) + ".", layout=layout.describe_layers(sizes))


def parameters_section(ctx: PromptContext) -> str:
    """The policy-structure section: the flat layout of params (D = (n_s + 1) n_a) and the box, encoded
    (theta~ = A theta, paper Sec. II-B: no range is stated) or raw. ValueError for an unknown encoding.

    An MLP (``ctx.hidden``) is described by its own piece (``mlp_structure``) in place of the linear
    policy's first line, followed by the same encoding text; unencoded, each layer's range is stated.
    """
    if ctx.hidden:
        return _mlp_parameters(ctx)
    desc = layout.describe(ctx.n_s, ctx.n_a, terse=ctx.numbers.terse)
    if ctx.encoded_params:
        if ctx.param_encoding not in _PARAM_TEMPLATES:
            raise ValueError(f"unknown parameter encoding {ctx.param_encoding!r}")
        text = render(_PARAM_TEMPLATES[ctx.param_encoding], layout=desc)
        if ctx.warmup_range is not None:
            low, high = ctx.warmup_range
            text += "\n" + render("warmup_note", low=fmt_value(low, ctx.decimals), high=fmt_value(high, ctx.decimals))
        return text
    if ctx.param_range is None:
        raise ValueError("unencoded parameters need a public range")
    low, high = ctx.param_range
    return render("parameters_raw", layout=desc, low=fmt_value(low, ctx.decimals), high=fmt_value(high, ctx.decimals))


def _mlp_parameters(ctx: PromptContext) -> str:
    """``parameters_section`` of an MLP: its structure, then the encoding's text after the linear
    policy's line (the templates' first line), or each layer's range for raw parameters."""
    head = mlp_structure(ctx)
    if ctx.encoded_params:
        if ctx.param_encoding not in _PARAM_TEMPLATES:
            raise ValueError(f"unknown parameter encoding {ctx.param_encoding!r}")
        rest = render(_PARAM_TEMPLATES[ctx.param_encoding], layout="").split("\n", 1)
        text = head + ("\n" + rest[1] if len(rest) > 1 else "")
        if ctx.warmup_range is not None:
            low, high = ctx.warmup_range
            text += "\n" + render("warmup_note", low=fmt_value(low, ctx.decimals), high=fmt_value(high, ctx.decimals))
        return text
    if ctx.layer_ranges is None:
        raise ValueError("unencoded parameters need a public range per layer")
    ranges = ", ".join(f"layer {n} (W{n}, b{n}) in [{fmt_value(lo, ctx.decimals)}, {fmt_value(hi, ctx.decimals)}]"
                       for n, (lo, hi) in enumerate(ctx.layer_ranges, start=1))
    return head + "\n" + render("layer_ranges", ranges=ranges)


def feedback_section(ctx: PromptContext) -> str:
    """The feedback section: what the printed returns mean (scaled r~ = c r, Sec. II-C, or raw), the
    optimum when disclosed, and the reward components and diagnostics with detailed feedback.
    """
    if ctx.scaled_rewards and ctx.reward_encoding not in _REWARD_NOTES:
        raise ValueError(f"unknown reward encoding {ctx.reward_encoding!r}")
    scale = render(wording(ctx, _REWARD_NOTES[ctx.reward_encoding])) if ctx.scaled_rewards else ""
    optimum = render("optimum_note", optimum=fmt(ctx.optimum, ctx.decimals)) if ctx.optimum is not None else ""
    if not ctx.detailed_feedback:
        return render(wording(ctx, "feedback_scalar"), scale_note=scale, optimum_note=optimum)
    notes = [f"- component {k}: {v}" for k, v in ctx.component_notes]
    notes += [f"- diagnostic {k}: {v}" for k, v in ctx.diagnostic_notes]
    return render(wording(ctx, "feedback_detailed"), scale_note=scale, optimum_note=optimum, notes="\n".join(notes)).rstrip()


def interaction_section(ctx: PromptContext) -> str:
    """The interaction section: how many past policies the history shows (top-K or all) and the answer format (D numbers)."""
    size = "every policy evaluated so far" if ctx.history_limit == 0 else f"at most the {ctx.history_limit} best policies so far"
    return render(wording(ctx, "interaction"), history_size=size, D=ctx.D, last=ctx.D - 1, numbers=ctx.numbers.words)


# Shared with ``wire.transcript``, which reads entries back out of recorded prompts.
COMPONENTS_PREFIX = "\ncomponents: "
DIAGNOSTICS_PREFIX = "\ndiagnostics: "


PARAMS_STYLES = {"list": "history_entry", "indexed": "history_entry_indexed"}
LAYOUTS = {"static-first": "prompt", "history-first": "prompt_history_first"}


def _choice(table: dict[str, str], value: str, what: str) -> str:
    if value not in table:
        raise ValueError(f"unknown {what} {value!r} (known: {', '.join(table)})")
    return table[value]


def params_text(ctx: PromptContext, params: tuple[float, ...]) -> str:
    """Parameters as the context's number format writes them (``ctx.numbers``: integers on the
    grid). The list form is the compact default: no space after a comma and ``param_digits``
    significant digits (one token per character saved with Gemma's tokenizer). The ProPS form
    repeats ``params[i]: `` before every value at fixed decimals. benchmarks/RESULTS.md compares
    the two in characters, tokens and search results."""
    d = ctx.param_decimals  # the number format's (wire.numbers): 0 on the grid
    if _choice(PARAMS_STYLES, ctx.params_style, "params style") == PARAMS_STYLES["list"]:
        return fmt_vector(params, d, digits=ctx.param_sig_digits, sep=",")
    return ", ".join(f"params[{i}]: {fmt(v, d)}" for i, v in enumerate(params))


def history_entry(ctx: PromptContext, e: EncodedEntry) -> str:
    """One history line: encoded params, encoded return, components and diagnostics in the chosen style.

    Raises TypeError for anything but an EncodedEntry (raw candidates never reach a prompt).
    """
    if not isinstance(e, EncodedEntry):  # a raw Candidate must never be formatted into a prompt
        raise TypeError(f"prompt history takes EncodedEntry values only, got {type(e).__name__}")
    d = ctx.decimals
    comps = diags = ""
    if ctx.detailed_feedback and e.components:
        comps = COMPONENTS_PREFIX + ", ".join(f"{k}={fmt(v, d)}" for k, v in e.components)
    if ctx.detailed_feedback and e.diagnostics:
        diags = DIAGNOSTICS_PREFIX + ", ".join(f"{k}={fmt_value(v, d)}" for k, v in e.diagnostics)
    params = params_text(ctx, e.params)  # checks the style
    return render(PARAMS_STYLES[ctx.params_style], params=params, ret=fmt(e.ret, d), components=comps, diagnostics=diags)


def build_prompt(ctx: PromptContext, history: Sequence[EncodedEntry]) -> str:
    """With the default static-first layout only the history (last) changes between
    iterations, so a server that caches prompt prefixes re-reads just that part."""
    name = _choice(LAYOUTS, ctx.layout, "prompt layout")
    hist = "\n\n".join(history_entry(ctx, e) for e in history) if history else "(empty)"
    return render(
        name,
        task=task_section(ctx),
        parameters=parameters_section(ctx),
        feedback=feedback_section(ctx),
        interaction=interaction_section(ctx),
        history=hist,
    )


def build_correction(reason: str, D: int) -> str:
    """The follow-up message after an unusable answer: ``reason`` in words and the D numbers wanted."""
    return render("correction", reason=reason, D=D)
