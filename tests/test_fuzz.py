"""The wire decoder fuzzer (quick_stream/bench/fuzz.py): CI runs 20,000 inputs, the benchmark 100,000."""
from quick_stream.bench import fuzz
from quick_stream.wire import decode


def test_seeds_are_valid_messages_of_every_type():
    assert {decode(s).type for s in fuzz.seeds()} == {"frame", "flow", "motion", "correction", "stabilized",
                                                       "stats", "end"}


def test_twenty_thousand_mutated_messages_never_crash_or_hang():
    r = fuzz.run(20_000, seed=1)
    assert r.crashes == [] and r.hangs == 0
    assert r.inputs == 20_000 and r.rejected > 10_000 and r.accepted > 100  # mutations both pass and fail
    assert all(p["inputs"] > 2_000 for p in r.per_mutator.values())
