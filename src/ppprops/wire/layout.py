"""Words for the flat parameter layout; must match ``ppprops.policy`` (tested): the linear policy's
(``describe``) and an MLP's, layer by layer (``describe_layers``)."""

from __future__ import annotations


def param_index(i: int, j: int, n_a: int) -> int:
    """Index of W[i, j] (observation i, action j) in the flat vector."""
    return i * n_a + j


def bias_index(j: int, n_s: int, n_a: int) -> int:
    """Index of the bias b[j] (action j) in the flat vector: after the n_s x n_a weights."""
    return n_s * n_a + j


def describe(n_s: int, n_a: int, *, terse: bool = False) -> str:
    """The layout in words for the prompt: which params form W (row by row) and which the bias b
    (``terse``: the same facts in fewer words, the grid format's wording)."""
    D = (n_s + 1) * n_a
    last_w = n_s * n_a - 1
    if not terse:
        return (
            f"params has {D} entries: params[0..{last_w}] form the {n_s}x{n_a} weight matrix W row by row, "
            f"so W[i][j] = params[i*{n_a} + j] links state i to action j; params[{n_s * n_a}..{D - 1}] are the "
            f"{n_a} biases b[j] = params[{n_s * n_a} + j]. Action j's output is u[j] = sum_i s[i]*W[i][j] + b[j]."
        )
    return (
        f"params has {D} entries: the {n_s}x{n_a} weights W row by row in params[0..{last_w}], W[i][j] = params[i*{n_a} + j] "
        f"(state i to action j), then the biases in params[{n_s * n_a}..{D - 1}], b[j] = params[{n_s * n_a} + j]; "
        f"u[j] = sum_i s[i]*W[i][j] + b[j]."
    )


def layer_offsets(sizes: tuple[int, ...]) -> list[int]:
    """Where each layer's weights start in the flat vector, for widths ``sizes`` = (n_s, *hidden, n_a)."""
    out, at = [], 0
    for i, o in zip(sizes[:-1], sizes[1:], strict=True):
        out.append(at)
        at += (i + 1) * o
    return out


def describe_layers(sizes: tuple[int, ...]) -> str:
    """An MLP's layout in words: each layer's weight matrix (row by row) then its biases, input to output."""
    parts = []
    for number, ((i, o), at) in enumerate(zip(zip(sizes[:-1], sizes[1:], strict=True), layer_offsets(sizes), strict=True), start=1):
        w_end, b_end = at + i * o, at + (i + 1) * o
        parts.append(f"params[{at}..{w_end - 1}] form the {i}x{o} matrix W{number} row by row "
                     f"(W{number}[i][j] = params[{at} + i*{o} + j]), params[{w_end}..{b_end - 1}] are the {o} biases b{number}")
    D = sum((i + 1) * o for i, o in zip(sizes[:-1], sizes[1:], strict=True))
    return f"params has {D} entries, layer by layer: " + "; ".join(parts) + "."
