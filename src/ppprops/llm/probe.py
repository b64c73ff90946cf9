"""Before a run makes its directory: is the configured endpoint an OpenAI-compatible API that answers?

``probe_endpoint`` asks the endpoint's model list once (``GET {base_url}/models``, through the ``openai`` SDK, which every
OpenAI-compatible server has: OpenAI, vLLM, Ollama, llama.cpp's server, LM Studio). A closed port,
no answer within the time allowed, an HTTP error, or an answer that is not a JSON model list (an
HTML page, a 404: ``--base-url`` points somewhere else) is one ``ConfigError`` line, before the
warm-up's episodes are spent. The probe carries nothing of the run (no prompt, no parameter, no
return: only the request line and the API key header), so it is not one of the run's LLM requests:
the recording client, the store and the audit never see it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from ..errors import ConfigError

if TYPE_CHECKING:
    from .settings import LLMConfig

PROBE_TIMEOUT_S = 10.0  # at most this long (or the run's --timeout, when shorter) for the model list


def probe_endpoint(llm: LLMConfig, api_key: str) -> None:
    """Ask ``llm.base_url``'s model list once (module docstring); return when it is one.

    ``api_key`` is sent as the bearer token (``llm.client.read_api_key``). Waits at most
    ``PROBE_TIMEOUT_S`` seconds, or ``llm.timeout_s`` when shorter. Nothing is retried: a server
    that is starting answers the next command.

    Raises:
        ConfigError: one line naming the endpoint and what it did (module docstring).
    """
    import openai

    if not llm.base_url:
        raise ValueError("probe_endpoint needs an endpoint's base_url (the embedded model has none)")
    base = llm.base_url.rstrip("/")
    url = f"{base}/models"
    timeout = min(PROBE_TIMEOUT_S, llm.timeout_s)
    where = f"the LLM endpoint {base} (--base-url)"
    try:
        with openai.OpenAI(base_url=base, api_key=api_key, timeout=timeout, max_retries=0) as client:
            answer = client.models.with_raw_response.list().http_response
    except openai.APITimeoutError:
        raise ConfigError(f"{where} did not answer GET {url} within {timeout:g} s (is it overloaded, or not an LLM server?)") from None
    except openai.APIConnectionError:
        raise ConfigError(f"cannot reach {where}: nothing accepts connections there (is the server running, on that host and port?)"
                          ) from None  # fmt: skip
    except openai.APIStatusError as e:
        answer = e.response
    status = answer.status_code
    if status in (401, 403):
        key = f"the key in ${llm.api_key_env}" if llm.api_key_env else "no API key (--api-key-env names none)"
        raise ConfigError(f"{where} refused {key}: HTTP {status} on GET {url}")
    if status == 404:
        raise ConfigError(f"{where} is not an OpenAI-compatible API root: GET {url} is not found (HTTP 404); "
                          "the root usually ends in /v1, e.g. http://localhost:8000/v1")  # fmt: skip
    if status >= 400:
        raise ConfigError(f"{where} answered HTTP {status} on GET {url}: {_snippet(answer.text)}")
    if not _is_model_list(answer):
        kind = answer.headers.get("content-type", "").split(";")[0] or "no content type"
        raise ConfigError(f"{where} is not an OpenAI-compatible API: GET {url} answered {kind} ({_snippet(answer.text)}), "
                          "not a JSON model list")  # fmt: skip


def _is_model_list(answer: Any) -> bool:
    """True for a JSON object with a ``data`` list (OpenAI's ``/models``; Ollama's and llama.cpp's too)."""
    try:
        doc = answer.json()
    except ValueError:
        return False
    return isinstance(doc, dict) and isinstance(doc.get("data"), list)


def _snippet(text: str, limit: int = 60) -> str:
    """The start of a body on one line, for an error message."""
    flat = " ".join(text.split())
    return repr(flat[:limit] + ("..." if len(flat) > limit else "")) if flat else "an empty body"
