import statistics

import pytest

from psl_ros.step_timing import StepTiming


def test_medians_per_phase_in_microseconds_and_cleared():
    timing = StepTiming(('wait', 'physics', 'state'))
    waits = [300_000, 100_000, 250_000, 900_000]
    for ns in waits:
        timing.add('wait', ns)
    timing.add('physics', 28_500)
    assert timing.medians_us() == {'wait': statistics.median(waits) / 1000, 'physics': 28.5}
    timing.clear()
    assert timing.medians_us() == {}
    with pytest.raises(KeyError):
        timing.add('unknown', 1)
