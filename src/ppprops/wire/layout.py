"""Words for the flat parameter layout; must match ``ppprops.policy`` (tested)."""

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
