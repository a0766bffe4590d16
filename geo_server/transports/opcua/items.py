"""Which sampled values a monitored item of ours is notified of: each item's own
sampling interval, trigger and deadband, and its values never going back in time.

Without any OPC UA library (the server turns the client's filter into an `ItemRule` and
asks it about each sample), after OPC UA 1.05 Part 4 §7.22.2 (DataChangeFilter) and
Part 8 §6.2 (PercentDeadband):

- an item is sampled every `every` GEO cycles, its own revised sampling interval: two
  items of one variable with different intervals each keep theirs;
- the deadband compares with the *last value notified* ("the last cached value"), not
  with the previous sample: a value that creeps by less than the deadband per sample is
  notified once it has crept past it;
- a percent deadband is a share of the variable's EURange; without an EURange, or
  outside 0-100 %, it is refused (Bad_DeadbandFilterInvalid);
- a deadband on a value that is not a number is refused (Bad_FilterNotAllowed);
- a sample older than the item's last notification (the first value is read when the
  item is made, samples of earlier cycles may still be on their way) is not notified.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

#: DataChangeTrigger (Part 4 §7.22.2)
STATUS_ONLY, STATUS_VALUE, STATUS_VALUE_TIMESTAMP = 0, 1, 2
#: DeadbandType (Part 4 §7.22.2)
NO_DEADBAND, ABSOLUTE, PERCENT = 0, 1, 2
#: The slowest sampling interval granted (ms): an hour.
SLOWEST_MS = 3_600_000.0


@dataclass(frozen=True)
class Sample:
    """What an item was last notified of, or is offered: status code, value, and the
    source timestamp (any ordered stamp: the cycle's FILETIME)."""

    status: int
    value: Any
    stamp: Any


@dataclass(frozen=True)
class ItemRule:
    """One monitored item's sampling and filter."""

    every: int = 1  # sampled every `every` GEO cycles
    trigger: int = STATUS_VALUE
    deadband: float = 0.0  # absolute (a percent deadband already converted)

    def notifies(self, last: Sample | None, new: Sample) -> bool:
        """Whether `new` is notified to an item last notified of `last`."""
        if last is None:
            return True
        if new.stamp < last.stamp:  # never back in time
            return False
        if new.status != last.status:
            return True
        if self.trigger == STATUS_ONLY:
            return False
        if self.trigger == STATUS_VALUE_TIMESTAMP and new.stamp != last.stamp:
            return True
        if same(new.value, last.value):
            return False
        if self.deadband > 0.0 and _number(new.value) and _number(last.value):
            if math.isnan(new.value) or math.isnan(last.value):
                return True  # (into or out of NaN: once, Part 4 §7.22.2)
            return bool(abs(new.value - last.value) > self.deadband)
        return True


def same(a: Any, b: Any) -> bool:
    """Equal values, NaN equal to NaN (a value that stays NaN is not a change)."""
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return bool(a == b)


def _number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def rule_for(
    every: int,
    trigger: int,
    deadband_type: int,
    deadband_value: float,
    *,
    numeric: bool,
    eu_range: tuple[float, float] | None,
) -> ItemRule | str:
    """The rule of a DataChangeFilter for a variable, or the name of the status code
    that refuses it."""
    if trigger not in (STATUS_ONLY, STATUS_VALUE, STATUS_VALUE_TIMESTAMP):
        return "BadMonitoredItemFilterInvalid"
    if deadband_type == NO_DEADBAND:
        return ItemRule(every, trigger)
    if deadband_type not in (ABSOLUTE, PERCENT):
        return "BadMonitoredItemFilterUnsupported"
    if trigger == STATUS_VALUE_TIMESTAMP:  # "the same behaviour as STATUS_VALUE" with a
        trigger = STATUS_VALUE  # deadband (Part 4 §7.22.2)
    if not numeric:
        return "BadFilterNotAllowed"
    if not math.isfinite(deadband_value) or deadband_value < 0.0:
        return "BadDeadbandFilterInvalid"
    if deadband_type == ABSOLUTE:
        return ItemRule(every, trigger, deadband_value)
    if eu_range is None or deadband_value > 100.0:
        return "BadDeadbandFilterInvalid"
    low, high = eu_range
    return ItemRule(every, trigger, deadband_value / 100.0 * (high - low))


def cycles_of(asked_ms: float, publishing_ms: float, cycle_ms: float) -> int:
    """A sampling interval in whole GEO cycles, at least one (Part 4 §5.13.1.2: 0 is
    the fastest practical rate, -1 the subscription's publishing interval); NaN is the
    fastest, anything above `SLOWEST_MS` (infinity too) the slowest."""
    if math.isnan(asked_ms):
        asked_ms = cycle_ms  # (no interval: the fastest; infinity is the slowest)
    elif asked_ms < 0.0:
        asked_ms = publishing_ms if math.isfinite(publishing_ms) else cycle_ms
    return max(1, round(min(max(asked_ms, cycle_ms), SLOWEST_MS) / cycle_ms))


__all__ = [
    "ABSOLUTE",
    "NO_DEADBAND",
    "PERCENT",
    "STATUS_ONLY",
    "STATUS_VALUE",
    "STATUS_VALUE_TIMESTAMP",
    "ItemRule",
    "Sample",
    "cycles_of",
    "rule_for",
    "same",
]
