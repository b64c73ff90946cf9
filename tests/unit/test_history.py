from hypothesis import given
from hypothesis import strategies as st

from ppprops.wire import EncodedEntry, top_k


def _e(i: int, r: float) -> EncodedEntry:
    return EncodedEntry(index=i, params=(float(i),), ret=r)


def test_top_k_keeps_the_best_ordered_best_last() -> None:
    entries = [_e(i, r) for i, r in enumerate([5.0, 1.0, 9.0, 3.0, 7.0])]
    assert [e.ret for e in top_k(entries, 3)] == [5.0, 7.0, 9.0]
    assert [e.ret for e in top_k(entries, 0)] == [1.0, 3.0, 5.0, 7.0, 9.0]
    assert [e.ret for e in top_k(entries, 10)] == [1.0, 3.0, 5.0, 7.0, 9.0]


def test_ties_put_the_newest_entry_last() -> None:
    entries = [_e(0, 2.0), _e(1, 2.0), _e(2, 1.0)]
    assert [e.index for e in top_k(entries, 2)] == [0, 1]


@given(st.lists(st.floats(-1e3, 1e3), min_size=0, max_size=40), st.integers(0, 50))
def test_top_k_properties(rets: list[float], k: int) -> None:
    entries = [_e(i, r) for i, r in enumerate(rets)]
    out = top_k(entries, k)
    assert len(out) == (len(rets) if k == 0 else min(k, len(rets)))
    assert [e.ret for e in out] == sorted(e.ret for e in out)
    if out:
        kept = {e.index for e in out}
        worst_kept = out[0].ret
        assert all(e.ret <= worst_kept for e in entries if e.index not in kept)
