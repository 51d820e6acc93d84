"""The README's test passes hand each xdist worker a share of the tests: each share must start
with its long timing-sensitive tests (conftest.long_ones_first_on_each_worker)."""

from __future__ import annotations

from conftest import long_ones_first_on_each_worker


class _Item:
    def __init__(self, name: str, long: bool) -> None:
        self.name, self.long = name, long

    def get_closest_marker(self, name: str) -> object:
        return True if self.long and name in ("realtime", "slow") else None


def test_each_worker_share_starts_with_its_long_ones_and_only_the_order_changes() -> None:
    items = [_Item(f"t{i}", i in (3, 10, 17, 25, 29, 33)) for i in range(40)]
    for workers in (1, 2, 3, 4):
        got = list(items)
        long_ones_first_on_each_worker(got, workers)  # type: ignore[arg-type]
        assert sorted(i.name for i in got) == sorted(i.name for i in items), workers
        share = len(items) // workers
        long_ones = [i for i in items if i.long]
        for k in range(workers):
            mine = long_ones[k::workers]
            assert got[k * share : k * share + len(mine)] == mine, (workers, k)
        assert [i for i in got if not i.long] == [i for i in items if not i.long]  # the rest keeps its order
