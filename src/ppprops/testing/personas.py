"""Server-and-model personas for the fault server: answers in the shapes real endpoints produce.

Each persona answers one chat-completions request (``PERSONAS``, and ``QUIRK_PERSONAS`` for single
quirks) or one completions request of the document form (``DOCUMENT_PERSONAS``) the way a given server and model are publicly
documented or reported to answer it: where the reasoning goes (a ``reasoning`` or
``reasoning_content`` field, ``<think>`` tags, a lone ``</think>``, gpt-oss harmony markup),
what happens when ``max_tokens`` runs out while reasoning (``finish_reason: "length"``), and
which request parameters it refuses, with which status and body. The comment on each persona
says what it is modelled on. Reasoning text quotes the best history entry of the prompt (as
printed), which is exactly what must never be taken as the proposal.

A persona returns a ``Reply``; ``Reply.answer`` is the new vector it meant to propose (None when
the reply holds none: an error, a cut-off answer, junk, a repeated history entry). Tests and the
soak compare what the run evaluated against these.
"""

from __future__ import annotations

import json
import random
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from ..wire.forms import DOCUMENT
from ..wire.transcript import history_entries

# What a persona's reasoning costs out of the token budget: more than a chat request's default
# budget before the client makes room for reasoning (24 + 8 D + 512 on CartPole: 616).
REASONING_TOKENS = 1000
EXPLANATION_TOKENS = 200  # what the chatty persona's explanation costs (four characters a token)
CONTEXT_TOKENS = 4096  # the context of the context_full personas' server
CUT_SHORT_PROMPT, CUT_SHORT_TOKENS = 1500, 10  # the usage of the cut_short persona's answers
SLOW_TOKENS_PER_S = 1000.0  # the generation speed of the slow CPU personas (they sleep for it)


@dataclass(frozen=True)
class Reply:
    """One HTTP reply of a persona: status, body bytes, content type, and ``answer``, the new vector
    (length D) it proposes, or None when the reply holds none."""

    status: int
    body: bytes
    content_type: str = "application/json"
    answer: list[float] | None = None


@dataclass
class Turn:
    """One request as a persona sees it."""

    body: dict[str, Any]
    D: int
    answer: list[float]  # the new vector this persona would propose
    rng: random.Random
    n: int  # the server's request number
    best: tuple[str, ...] | None = None  # the best history entry, as the prompt printed it
    indexed: bool = False  # the prompt prints parameters as params[i]: v
    corrected: bool = False  # the conversation already holds a correction
    model: str = "fault-synthetic"
    extra: dict[str, Any] = field(default_factory=dict)
    document: bool = False  # a completions request of the document form (``prompt``, no messages)

    @property
    def budget(self) -> int | None:
        """The answer's token limit, under whichever name the client sent it."""
        for key in ("max_completion_tokens", "max_tokens"):
            v = self.body.get(key)
            if isinstance(v, int):
                return v
        return None

    @property
    def schema(self) -> bool:
        """True when the request asks for a ``json_schema`` response format."""
        rf = self.body.get("response_format")
        return isinstance(rf, dict) and rf.get("type") == "json_schema"


def read_turn(body: dict[str, Any], D: int, answer: list[float], rng: random.Random, n: int) -> Turn:
    """The Turn of request number ``n``: its chat (or completions) ``body``, the vector length ``D``,
    the ``answer`` to propose, and what the first message (or the document) shows (the best history
    entry of length D, the indexed form, whether a correction was already made)."""
    if isinstance(body.get("prompt"), str):  # the document form: history lowest return first, best last
        entries = [e for e in DOCUMENT.entries(body["prompt"]) if len(e.params) == D]
        return Turn(body=body, D=D, answer=answer, rng=rng, n=n, best=entries[-1].params if entries else None,
                    model=str(body.get("model") or "fault-synthetic"), document=True)
    messages = [m for m in body.get("messages") or [] if isinstance(m, dict)]
    prompt = str(messages[0].get("content") or "") if messages else ""
    entries = [e for e in history_entries(prompt) if len(e.params) == D]
    corrected = len(messages) > 1 or "could not be used" in prompt
    return Turn(body=body, D=D, answer=answer, rng=rng, n=n, best=entries[-1].params if entries else None,
                indexed="params[0]: " in prompt, corrected=corrected, model=str(body.get("model") or "fault-synthetic"))


# -- building blocks ------------------------------------------------------------------------------
def params_json(values: list[Any]) -> str:
    """The answer object the prompt asks for, ``{"params": [v0, v1, ...]}``, each value as ``str`` prints it."""
    return '{"params": [' + ", ".join(str(v) for v in values) + "]}"


def quote(turn: Turn) -> str:
    """The best history entry as the prompt printed it (a random stand-in without history)."""
    vals = turn.best or tuple(f"{turn.rng.uniform(-3, 3):.2f}" for _ in range(turn.D))
    if turn.indexed:
        return ", ".join(f"params[{i}]: {v}" for i, v in enumerate(vals))
    return "[" + ",".join(vals) + "]"


def analysis(turn: Turn) -> str:
    """gpt-oss-like reasoning: quotes the best history entry, drafts an answer object, then moves on."""
    draft = params_json([round(turn.rng.uniform(-3, 3), 2) for _ in range(turn.D)])
    return (f"We need to output new params. The history is sorted by return. The best so far is {quote(turn)}, "
            f"with the highest return. The pole angle weights look too small. Draft: {draft}. Hmm, too far; "
            "change a few weights moderately and keep the rest.")


def cut(text: str) -> str:
    """Reasoning stopped by the token limit: a little past the quoted entry."""
    at = text.find("]") if "]" in text else len(text) // 2
    return text[: at + 40]


def short_of_budget(turn: Turn, answer_text: str) -> bool:
    """True when the request's token limit cannot hold REASONING_TOKENS plus ``answer_text``
    (four characters a token); False when the request sets no limit."""
    budget = turn.budget
    return budget is not None and budget < REASONING_TOKENS + len(answer_text) // 4 + 1


def completion(turn: Turn, content: str | None, *, message: dict[str, Any] | None = None, finish: str = "stop",
               reasoning_tokens: int | None = None, answer: list[float] | None = None) -> Reply:
    """A 200 chat-completion body with ``content`` (and the extra ``message`` fields), ``finish`` as
    its finish_reason and a usage block (four characters a token, plus ``reasoning_tokens``)."""
    msg: dict[str, Any] = {"role": "assistant", "content": content}
    msg.update(message or {})
    visible = len(content or "") + sum(len(v) for v in (message or {}).values() if isinstance(v, str))
    tokens = visible // 4 + 1 + (reasoning_tokens or 0)
    if finish == "length" and turn.budget is not None:
        tokens = turn.budget  # cut off at the token limit: the whole budget was spent
    usage: dict[str, Any] = {"prompt_tokens": 0, "completion_tokens": tokens, "total_tokens": tokens}
    if reasoning_tokens is not None:
        usage["completion_tokens_details"] = {"reasoning_tokens": reasoning_tokens}
    doc = {
        "id": f"chatcmpl-persona-{turn.n}",
        "object": "chat.completion",
        "created": int(time.time()),
        "model": turn.model,
        "choices": [{"index": 0, "message": msg, "finish_reason": finish}],
        "usage": usage,
    }
    return Reply(200, json.dumps(doc).encode(), answer=answer)


def text_completion(turn: Turn, text: str, *, finish: str = "stop", answer: list[float] | None = None,
                    prompt_tokens: int = 0, completion_tokens: int | None = None) -> Reply:
    """A 200 completions body (``object: text_completion``) whose one choice continues the
    document with ``text``; the usage counts four characters a token, or ``completion_tokens``."""
    tokens = len(text) // 4 + 1 if completion_tokens is None else completion_tokens
    doc = {
        "id": f"cmpl-persona-{turn.n}",
        "object": "text_completion",
        "created": int(time.time()),
        "model": turn.model,
        "choices": [{"index": 0, "text": text, "logprobs": None, "finish_reason": finish}],
        "usage": {"prompt_tokens": prompt_tokens, "completion_tokens": tokens, "total_tokens": prompt_tokens + tokens},
    }
    return Reply(200, json.dumps(doc).encode(), answer=answer)


def labelled_list(values: list[Any]) -> str:
    """The continuation of the document form's open list: ``0:v0,1:v1,...`` and the closing ``]``."""
    return ",".join(f"{i}:{v}" for i, v in enumerate(values)) + "]"


def error(status: int, doc: Any) -> Reply:
    """An error reply: ``status`` with the JSON of ``doc`` as its body."""
    return Reply(status, json.dumps(doc).encode())


# -- personas -------------------------------------------------------------------------------------
def plain(turn: Turn) -> Reply:
    """Any non-reasoning model: the requested JSON object and nothing else."""
    return completion(turn, params_json(turn.answer), answer=turn.answer)


def vllm_gpt_oss(turn: Turn) -> Reply:
    """vLLM with gpt-oss: analysis in ``message.reasoning``, the answer in content; cut off: content null, "length"."""
    # vLLM serving gpt-oss with --reasoning-parser openai_gptoss: the analysis channel in
    # message.reasoning (vLLM renamed reasoning_content to reasoning, vllm-project/vllm#27752,
    # docs.vllm.ai features/reasoning_outputs), the final channel in content, plus vLLM's empty
    # refusal/tool_calls fields. Out of max_tokens while reasoning: content null, finish "length".
    ans = params_json(turn.answer)
    fields: dict[str, Any] = {"refusal": None, "annotations": None, "tool_calls": []}
    if short_of_budget(turn, ans):
        return completion(turn, None, message={**fields, "reasoning": cut(analysis(turn))}, finish="length")
    return completion(turn, ans, message={**fields, "reasoning": analysis(turn)}, answer=turn.answer)


def vllm_gpt_oss_final_in_reasoning(turn: Turn) -> Reply:
    """vLLM with gpt-oss, final channel filed under reasoning: content null, the answer at the end of ``reasoning``."""
    # vLLM gpt-oss when the parser files the final channel under reasoning (vllm-project/vllm#23694):
    # content null, the reasoning holds the analysis (quoting the history) and then the final JSON.
    ans = params_json(turn.answer)
    if short_of_budget(turn, ans):
        return completion(turn, None, message={"reasoning": cut(analysis(turn))}, finish="length")
    return completion(turn, None, message={"reasoning": analysis(turn) + "\n" + ans}, answer=turn.answer)


OLLAMA_SCHEMA_JUNK = 'The user says "\n\n    \t}\n       \t\t \t\t    '


def ollama_gpt_oss(turn: Turn) -> Reply:
    """Ollama with gpt-oss: thinking in ``reasoning`` (off for reasoning_effort "none"); junk content under a json_schema."""
    # Ollama's OpenAI-compatible /v1 with gpt-oss: thinking in message.reasoning and the answer in
    # content (ollama/ollama#15288); reasoning_effort "none" turns thinking off (ollama#12004 as
    # cited in aictrl-dev/cli#75); under a json_schema response_format gpt-oss returns junk content
    # (ollama/ollama#11691, the junk quoted from it); out of tokens while thinking: content "",
    # finish "length".
    thinking = turn.body.get("reasoning_effort") != "none"
    ans = params_json(turn.answer)
    if thinking and short_of_budget(turn, ans):
        return completion(turn, "", message={"reasoning": cut(analysis(turn))}, finish="length")
    if turn.schema:
        return completion(turn, OLLAMA_SCHEMA_JUNK, message={"reasoning": analysis(turn)} if thinking else None)
    return completion(turn, ans, message={"reasoning": analysis(turn)} if thinking else None, answer=turn.answer)


def llamacpp_gpt_oss(turn: Turn) -> Reply:
    """llama-server with gpt-oss: analysis in ``reasoning_content``, the answer in content; cut off: content "", "length"."""
    # llama.cpp llama-server --jinja with the default --reasoning-format (auto): harmony parsed into
    # reasoning_content and content (ggml-org/llama.cpp#15181); out of tokens: content "", "length".
    ans = params_json(turn.answer)
    if short_of_budget(turn, ans):
        return completion(turn, "", message={"reasoning_content": cut(analysis(turn))}, finish="length")
    return completion(turn, ans, message={"reasoning_content": analysis(turn)}, answer=turn.answer)


HARMONY_TEMPLATE_ERROR = (
    "You have passed a message containing <|channel|> tags in the content field. Instead of doing this, you should "
    "pass analysis messages (the string between '<|message|>' and '<|end|>') in the 'thinking' field, and final "
    "messages (the string between '<|message|>' and '<|end|>') in the 'content' field."
)


def harmony_markup(turn: Turn) -> Reply:
    """Raw gpt-oss harmony markup in content; HTTP 500 when an assistant turn sent back holds ``<|channel|>`` tags."""
    # llama.cpp with --reasoning-format none (or a build before harmony parsing): the raw harmony
    # markup in content, "<|channel|>analysis<|message|>...<|end|><|start|>assistant<|channel|>final
    # <|message|>..." (ggml-org/llama.cpp#15181). Its gpt-oss chat template raises on an assistant
    # turn holding <|channel|> tags, and llama-server answers HTTP 500 with that message
    # (reported in ggml-org/llama.cpp#15091).
    for m in turn.body.get("messages") or []:
        if isinstance(m, dict) and m.get("role") == "assistant" and "<|channel|>" in str(m.get("content")):
            return error(500, {"error": {"code": 500, "message": HARMONY_TEMPLATE_ERROR, "type": "server_error"}})
    ans = params_json(turn.answer)
    if short_of_budget(turn, ans):
        return completion(turn, "<|channel|>analysis<|message|>" + cut(analysis(turn)), finish="length")
    content = ("<|channel|>analysis<|message|>" + analysis(turn) + "<|end|><|start|>assistant<|channel|>final<|message|>"
               + ans)
    return completion(turn, content, answer=turn.answer)


def harmony_markup_repeats_once(turn: Turn) -> Reply:
    """``harmony_markup`` whose first final answer repeats the best history entry; a new vector once corrected."""
    # The harmony_markup server, with a final channel that first repeats the best history entry
    # (so the client must correct it, and an assistant turn that echoed the markup would get the 500).
    if turn.best is not None and not turn.corrected:
        reply = harmony_markup(turn)
        if reply.answer is None:  # the template error, or an answer cut off at the token limit
            return reply
        repeated = '{"params": [' + ", ".join(turn.best) + "]}"
        content = ("<|channel|>analysis<|message|>" + analysis(turn) + "<|end|><|start|>assistant<|channel|>final"
                   "<|message|>" + repeated)
        return completion(turn, content)
    return harmony_markup(turn)


def r1_thought(turn: Turn) -> str:
    """R1-style thinking: quotes the best entry, drafts an answer object, then revises it."""
    draft = params_json([round(turn.rng.uniform(-3, 3), 2) for _ in range(turn.D)])
    return (f"Okay, let me look at the history. The best entry is {quote(turn)}. I should move away from it a "
            f"little. Maybe {draft}? Wait, that changes too much. Let me adjust fewer weights.\n")


def r1_open_think(turn: Turn) -> Reply:
    """An R1 distill whose reasoning is not split out: reasoning, a lone ``</think>``, then the answer, all in content."""
    # DeepSeek-R1 distills behind a server that does not split reasoning (llama.cpp
    # --reasoning-format none, vLLM without --reasoning-parser): the chat template opens <think> in
    # the prompt, so the content is reasoning, a lone "</think>", then the answer.
    content = r1_thought(turn) + "</think>\n\n" + params_json(turn.answer)
    return completion(turn, content, answer=turn.answer)


def r1_think_tags(turn: Turn) -> Reply:
    """An R1-style model with ``<think>...</think>`` and then the answer in content."""
    # R1-style models served with the reasoning left in content, <think>...</think> then the answer
    # (Ollama before it split thinking out, ollama/ollama#9137).
    content = "<think>\n" + r1_thought(turn) + "</think>\n\n" + params_json(turn.answer)
    return completion(turn, content, answer=turn.answer)


def deepseek_reasoner(turn: Turn) -> Reply:
    """DeepSeek's deepseek-reasoner: ``reasoning_content`` and content; a json_schema response_format gets a plain-text 422."""
    # DeepSeek's API with deepseek-reasoner: reasoning_content and content (api-docs.deepseek.com,
    # reasoning model guide). Its JSON output takes {"type": "json_object"} only; a json_schema
    # response_format gets HTTP 422 with a plain-text body (quoted in browser-use/browser-use#215
    # and dzhng/deep-research#22).
    if turn.schema:
        text = ("Failed to deserialize the JSON body into the target type: response_format: response_format.type "
                f"`json_schema` is unavailable now at line 1 column {len(json.dumps(turn.body))}")
        return Reply(422, text.encode(), "text/plain; charset=utf-8")
    return completion(turn, params_json(turn.answer), message={"reasoning_content": r1_thought(turn)},
                      answer=turn.answer)


def openai_reasoning(turn: Turn) -> Reply:
    """OpenAI reasoning models: 400 for ``max_tokens`` or a temperature other than 1; hidden reasoning counted in usage."""
    # OpenAI's reasoning models (o-series, gpt-5) on chat completions: max_tokens is refused in
    # favour of max_completion_tokens, a temperature other than 1 is refused (error bodies as quoted
    # in microsoft/vscode-copilot-release#8065 and holoviz/lumen#1087); the reasoning is hidden but
    # counted in usage.completion_tokens_details.reasoning_tokens and against max_completion_tokens;
    # out of budget: content "" and finish "length".
    if "max_tokens" in turn.body:
        return error(400, {"error": {
            "message": "Unsupported parameter: 'max_tokens' is not supported with this model. "
                       "Use 'max_completion_tokens' instead.",
            "type": "invalid_request_error", "param": "max_tokens", "code": "unsupported_parameter"}})
    t = turn.body.get("temperature")
    if t is not None and t != 1:
        return error(400, {"error": {
            "message": f"Unsupported value: 'temperature' does not support {t} with this model. "
                       "Only the default (1) value is supported.",
            "type": "invalid_request_error", "param": "temperature", "code": "unsupported_value"}})
    ans = params_json(turn.answer)
    if short_of_budget(turn, ans):
        return completion(turn, "", finish="length", reasoning_tokens=turn.budget)
    return completion(turn, ans, reasoning_tokens=REASONING_TOKENS, answer=turn.answer)


def gemini_openai(turn: Turn) -> Reply:
    """Gemini's OpenAI-compatible endpoint: a list-wrapped 400 for a ``seed`` field, else the plain answer."""
    # Gemini's OpenAI-compatible endpoint refusing a field it does not know: HTTP 400 with a
    # list-wrapped google.rpc error, 'Invalid JSON payload received. Unknown name "seed": Cannot
    # find field.' (the shape quoted in MinLL/SkyrimNet-GamePlugin#77 and Alishahryar1/free-claude-code#542).
    if "seed" in turn.body:
        msg = 'Invalid JSON payload received. Unknown name "seed": Cannot find field.'
        return error(400, [{"error": {"code": 400, "message": msg, "status": "INVALID_ARGUMENT", "details": [
            {"@type": "type.googleapis.com/google.rpc.BadRequest", "fieldViolations": [{"description": msg}]}]}}])
    return completion(turn, params_json(turn.answer), answer=turn.answer)


def restates_history(turn: Turn) -> Reply:
    """A chatty model: restates the best entry as ``params[i]: v`` pairs, then gives the answer object."""
    # A chatty instruct model that restates the best entry in the ProPS form (params[i]: v, the
    # form of the ProPS paper's prompts) before giving the JSON object the prompt asks for.
    vals = turn.best or tuple(f"{v:.2f}" for v in turn.answer)
    restated = ", ".join(f"params[{i}]: {v}" for i, v in enumerate(vals))
    content = f"The best policy so far is {restated}.\nI will change a few of them:\n{params_json(turn.answer)}"
    return completion(turn, content, answer=turn.answer)


def unicode_minus(turn: Turn) -> Reply:
    """The answer object with its minus signs typeset as U+2212 or en dashes."""
    # Answers typeset with U+2212 minus signs or en dashes, as models trained on typeset text write them.
    text = ", ".join(str(v).replace("-", turn.rng.choice(["\u2212", "\u2013"])) for v in turn.answer)
    return completion(turn, '{"params": [' + text + "]}", answer=turn.answer)


def repeats_history_once(turn: Turn) -> Reply:
    """First proposes the best history entry again, as printed; a new vector once corrected."""
    # A model that first proposes the best history entry again, as printed, and a new policy once told.
    if turn.best is not None and not turn.corrected:
        return completion(turn, '{"params": [' + ", ".join(turn.best) + "]}")
    return completion(turn, params_json(turn.answer), answer=turn.answer)


def chatty_explainer(turn: Turn) -> Reply:
    """An instruction-tuned chat model that explains before it answers (about ``EXPLANATION_TOKENS``);
    cut off at the token limit when the budget cannot hold both; a JSON schema holds it to the object."""
    # Instruction-tuned chat models (Qwen2.5-Coder-1.5B-Instruct, SmolLM2-135M-Instruct behind
    # llama.cpp) write a paragraph on the history before the answer object unless a JSON
    # schema holds them to it; at 24 + 8 D tokens that cut off 2 of 14 and 30 of 45 answers.
    ans = params_json(turn.answer)
    if turn.schema:
        return completion(turn, ans, answer=turn.answer)
    words = ("Looking at the history, the best policy puts most weight on the pole angle and its velocity. "
             "Returns rise as those weights grow, while the cart position weights matter less. ")
    explanation = (words * (EXPLANATION_TOKENS * 4 // len(words) + 1))[: EXPLANATION_TOKENS * 4]
    budget = turn.budget
    if budget is not None and budget < EXPLANATION_TOKENS + len(ans) // 4 + 1:
        return completion(turn, explanation[: budget * 4], finish="length")
    return completion(turn, explanation + "\n\nMy proposal:\n" + ans, answer=turn.answer)


def bullet_list_once(turn: Turn) -> Reply:
    """A small chat model that first answers with a bullet list of only 4 of the D numbers; the
    answer object once corrected."""
    # SmolLM2-135M-Instruct without a schema: a bullet list holding 4 of the 10 numbers.
    if not turn.corrected:
        items = "\n".join(f"- {v}" for v in turn.answer[:4])
        return completion(turn, f"Here are the new parameters:\n{items}")
    return completion(turn, params_json(turn.answer), answer=turn.answer)


def llamacpp_forced_think(turn: Turn) -> Reply:
    """llama.cpp with a chat template that forces ``<think>`` open: everything, the answer object
    included, in ``reasoning_content``; content empty; a JSON schema is not enforced."""
    # llama-server --jinja with a template that opens <think> in the prompt (dependencies.md,
    # 2026-12-01): the reasoning parser files the whole answer under reasoning_content, and the
    # json_schema grammar is not applied to it.
    ans = params_json(turn.answer)
    return completion(turn, "", message={"reasoning_content": r1_thought(turn) + "So my answer is " + ans},
                      answer=turn.answer)


def context_full(turn: Turn) -> Reply:
    """A server whose context (``CONTEXT_TOKENS``) is full: the answer stops with finish_reason
    "length" before the budget is spent, prompt and answer together filling the context."""
    # llama.cpp when prompt + answer reach its context size (dependencies.md, 2026-12-01):
    # finish_reason "length", total tokens equal to the context, whatever max_tokens was.
    written = min(20, max(1, (turn.budget or 40) // 2))
    prompt_tokens = CONTEXT_TOKENS - written
    if turn.document:
        return text_completion(turn, ",".join(f"{i}:{v}" for i, v in enumerate(turn.answer[:2])), finish="length",
                               prompt_tokens=prompt_tokens, completion_tokens=written)
    doc = json.loads(completion(turn, params_json(turn.answer)[:40], finish="length").body)
    doc["usage"] = {"prompt_tokens": prompt_tokens, "completion_tokens": written, "total_tokens": CONTEXT_TOKENS}
    return Reply(200, json.dumps(doc).encode())


def slow_cpu_reasoner(turn: Turn) -> Reply:
    """A reasoning model on a CPU llama.cpp server: ``SLOW_TOKENS_PER_S`` tokens a second (it
    sleeps for them), ``REASONING_TOKENS`` of reasoning in ``reasoning_content`` before the answer;
    cut off at the token limit when the budget cannot hold them."""
    # llama-server on CPU cores with a reasoning model: 7 tokens/s against a budget of
    # 8,296 tokens is about 20 minutes, past a 300 s timeout; here everything is 1000 times faster.
    ans = params_json(turn.answer)
    if short_of_budget(turn, ans):
        time.sleep((turn.budget or 0) / SLOW_TOKENS_PER_S)
        return completion(turn, "", message={"reasoning_content": cut(analysis(turn))}, finish="length")
    time.sleep((REASONING_TOKENS + len(ans) // 4 + 1) / SLOW_TOKENS_PER_S)
    return completion(turn, ans, message={"reasoning_content": analysis(turn)}, reasoning_tokens=REASONING_TOKENS,
                      answer=turn.answer)


def needs_schema(turn: Turn) -> Reply:
    """A small model that answers the JSON object when a JSON schema holds it to it, and prose with
    no numbers when nothing does."""
    # Gemma 3 270M (the embedded model) behind a fault-injecting proxy, asked in the chat form: under
    # a json_schema response_format (which llama.cpp turns into a grammar) every answer it wrote was
    # the object; once the schema was dropped, every answer was unusable.
    if turn.schema:
        return completion(turn, params_json(turn.answer), answer=turn.answer)
    return completion(turn, "Sure! A better policy pushes the cart towards the side the pole leans to.")


def cut_short(turn: Turn) -> Reply:
    """An answer cut short on its way (a proxy, a server): ``finish_reason`` "length" after
    ``CUT_SHORT_TOKENS`` completion tokens, far below the budget sent, with a prompt far from any
    context size (``CUT_SHORT_PROMPT`` tokens)."""
    # A fault-injecting proxy in front of llama.cpp that cut answers: 10 completion tokens,
    # finish_reason "length", the budget and the context nowhere near.
    doc = json.loads(completion(turn, params_json(turn.answer)[:40], finish="length").body)
    total = CUT_SHORT_PROMPT + CUT_SHORT_TOKENS
    doc["usage"] = {"prompt_tokens": CUT_SHORT_PROMPT, "completion_tokens": CUT_SHORT_TOKENS, "total_tokens": total}
    return Reply(200, json.dumps(doc).encode())


PERSONAS: dict[str, Callable[[Turn], Reply]] = {
    "plain": plain,
    "vllm_gpt_oss": vllm_gpt_oss,
    "vllm_gpt_oss_final_in_reasoning": vllm_gpt_oss_final_in_reasoning,
    "ollama_gpt_oss": ollama_gpt_oss,
    "llamacpp_gpt_oss": llamacpp_gpt_oss,
    "harmony_markup": harmony_markup,
    "harmony_markup_repeats_once": harmony_markup_repeats_once,
    "r1_open_think": r1_open_think,
    "r1_think_tags": r1_think_tags,
    "deepseek_reasoner": deepseek_reasoner,
    "openai_reasoning": openai_reasoning,
    "gemini_openai": gemini_openai,
    "restates_history": restates_history,
    "unicode_minus": unicode_minus,
    "repeats_history_once": repeats_history_once,
}
# Chat personas for single quirks, named one by one and never drawn by "all" (``PERSONAS``): a full
# context never gives a usable answer, the slow server sleeps, and adding them to ``PERSONAS``
# would change the sequence a seeded server draws from it.
QUIRK_PERSONAS: dict[str, Callable[[Turn], Reply]] = {
    "chatty_explainer": chatty_explainer,
    "bullet_list_once": bullet_list_once,
    "llamacpp_forced_think": llamacpp_forced_think,
    "context_full": context_full,
    "slow_cpu_reasoner": slow_cpu_reasoner,
    "needs_schema": needs_schema,
    "cut_short": cut_short,
}


# -- the document form (the completions endpoint) -----------------------------------------------------
def document_plain(turn: Turn) -> Reply:
    """A base model held to the open list (a grammar, or a well-behaved model): the D values and ``]``."""
    return text_completion(turn, labelled_list(turn.answer), answer=turn.answer)


def base_model_runs_on(turn: Turn) -> Reply:
    """A base model that closes the list and then writes more document (another entry, and another)
    until the token limit. A ``stop`` sequence ends it there (the stop text is not returned, as
    llama.cpp, vLLM and OpenAI do); a ``grammar`` ends it at ``]``. Neither: cut off, "length"."""
    # Gemma 3 270M behind a remote llama-server, continuing the document without a grammar
    # (twice 18 of 18 iterations): after the list it writes "return: ...", "params: [...",
    # and so on until max_tokens, so every answer ended with finish_reason "length".
    listed = labelled_list(turn.answer)
    more = "".join(f"\n\nreturn: {100 + 10 * k:.2f}\nparams: [" + labelled_list([round(turn.rng.uniform(-3, 3), 2)
                                                                                    for _ in range(turn.D)])
                   for k in range(50))
    text = listed + more
    if isinstance(turn.body.get("grammar"), str):
        return text_completion(turn, listed, answer=turn.answer)
    stops = turn.body.get("stop")
    stops = [stops] if isinstance(stops, str) else [x for x in stops or [] if isinstance(x, str) and x]
    cuts = [text.find(x) for x in stops if x in text]
    if cuts:
        return text_completion(turn, text[: min(cuts)], answer=turn.answer)
    budget = turn.budget
    if budget is not None and len(text) // 4 >= budget:
        return text_completion(turn, text[: budget * 4], finish="length", completion_tokens=budget)
    return text_completion(turn, text, answer=turn.answer)


def strict_completions(turn: Turn) -> Reply:
    """A completions endpoint that does not know llama.cpp's ``grammar``: HTTP 400 naming it; else
    ``base_model_runs_on`` (``stop`` honoured)."""
    # OpenAI's API answers a field it does not know with HTTP 400, "Unrecognized request argument
    # supplied: <name>" (invalid_request_error, param null), as quoted in openai/openai-python#1166
    # and BerriAI/litellm#1233.
    if "grammar" in turn.body:
        return error(400, {"error": {"message": "Unrecognized request argument supplied: grammar",
                                     "type": "invalid_request_error", "param": None, "code": None}})
    return base_model_runs_on(turn)


# A persona named here answers completions requests; any other answers them as ``document_plain``
# (and a persona named only here answers chat requests as ``plain``).
DOCUMENT_PERSONAS: dict[str, Callable[[Turn], Reply]] = {
    "plain": document_plain,
    "base_model_runs_on": base_model_runs_on,
    "context_full": context_full,
    "strict_completions": strict_completions,
}
