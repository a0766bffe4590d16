"""OPC UA's monitored items of the machines' variables (docs/design.md §9.1): their
rules (`items.ItemRule`: an interval in whole GEO cycles, a filter), the cycles the
engine publishes for them (`Demand`, the engine's `CycleDemand`), and the sampling of
those cycles on asyncua's loop, each cycle's changed values to the items of their
variables as asyncua's `datachange_callback` would, drawn on OPC UA's share of
notifications (`OpcUaOptions.loop_share`).

`OpcUaInterface` (server.py) owns one `Monitoring` and routes asyncua's
CreateMonitoredItems, ModifyMonitoredItems, SetMonitoringMode and its data-change
callbacks of our variables through it; everything runs on asyncua's loop but the
engine's `Demand.wants` (the engine's thread: two fields) and `_sampling`'s hand-over
(the cycle's thread: a deque and a wake-up).
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import math
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from geo_server.seam import OpcUaService
from geo_server.service import varies_at_rest
from geo_server.snapshot import Snapshot
from geo_server.transports.opcua import internals
from geo_server.transports.opcua.cnc import Live
from geo_server.transports.opcua.internals import ua as _ua
from geo_server.transports.opcua.items import (
    STATUS_VALUE_TIMESTAMP,
    ItemRule,
    Sample,
    cycles_of,
    rule_for,
    same,
)
from geo_server.transports.opcua.metering import RequestMeter
from geo_server.transports.opcua.space import VariableSpec
from geo_server.transports.share import LoopShare

#: Snapshots waiting to be sampled, per machine, while the loop is behind; older ones
#: are dropped (counted in `samples_late`).
SAMPLE_QUEUE = 256
#: monitored items notified of one value before the loop's other work runs (a thousand
#: items of one variable took 30-40 ms in one go)
NOTIFY_SLICE = 64
#: FILETIME's zero, OPC UA's DateTime epoch: a snapshot's stamp counts from it, and a
#: DataValue without a source time compares as one stamped then
FILETIME_EPOCH = dt.datetime(1601, 1, 1, tzinfo=dt.UTC)


@dataclass
class Var:
    """A variable node of one machine and its sampling state: an object of the
    dictionary (`spec`), or a read-only variable of a companion model computed from
    objects (`live`, `cnc.py`)."""

    spec: VariableSpec | None
    service: OpcUaService
    machine: str
    node_id: Any  # ua.NodeId
    vtype: Any = None  # ua.VariantType of its values
    attval: Any = None  # asyncua's AttributeValue of its Value (the items' callbacks)
    live: Live | None = None
    monitors: int = 0
    #: its items' sampling intervals (cycles) -> how many items sample at each
    rates: dict[int, int] = field(default_factory=dict)
    #: sampling interval -> the value sampled last at it (`_notify_snapshot`)
    lasts: dict[int, Any] = field(default_factory=dict)
    #: items notified on every sample, changed or not (trigger StatusValueTimestamp)
    stamped: int = 0

    def value(self, snap: Snapshot) -> Any:
        """Its value in the cycle of `snap`."""
        if self.live is not None:
            return self.live.read(snap)
        assert self.spec is not None
        return snap.value(self.spec.obj, self.spec.axis)

    @property
    def readable(self) -> bool:
        return self.spec.readable if self.spec is not None else True

    @property
    def ua_type(self) -> str:
        return self.spec.ua_type if self.spec is not None else self._live().ua_type

    @property
    def eu_range(self) -> tuple[float, float] | None:
        return self.spec.eu_range if self.spec is not None else None

    @property
    def numeric(self) -> bool:
        """A number a deadband applies to (Part 4 §7.22.2: not a flag, a text, an
        enumeration or a structure)."""
        if self.spec is not None:
            return self.spec.ua_type not in ("Boolean", "String")
        return self._live().number

    @property
    def at_rest(self) -> bool:
        """Whether it can change while the machine rests (`varies_at_rest`)."""
        if self.spec is not None:
            return varies_at_rest(self.spec.obj)
        return any(varies_at_rest(o) for o in self._live().sources)

    def _live(self) -> Live:
        assert self.live is not None
        return self.live

    @property
    def every(self) -> int:
        """Sampled every `every` cycles: each of its items' intervals is a multiple."""
        return math.gcd(*self.rates) if self.rates else 1

    def count(self, rule: ItemRule, delta: int) -> None:
        """An item of `rule` added (+1) or removed (-1); the samples at its interval
        are compared afresh (a new item's first value was read, not sampled)."""
        left = self.rates.get(rule.every, 0) + delta
        if left > 0:
            self.rates[rule.every] = left
        else:
            self.rates.pop(rule.every, None)
        self.lasts.pop(rule.every, None)
        self.stamped += delta if rule.trigger == STATUS_VALUE_TIMESTAMP else 0


class Demand:
    """The cycles the monitored variables of one machine need (the engine's
    `CycleDemand`, docs/design.md §13): every `step`-th cycle, and while the machine is at
    rest only when one of them can change at rest (`geo_server.service.varies_at_rest`):
    the others cannot change then, so there is nothing to notify. Called on the engine's
    thread: it only reads two fields the loop sets."""

    def __init__(self, step: int = 1, at_rest: bool = False) -> None:
        self.step = step
        self.at_rest = at_rest
        #: told of each change (`set`): OPC UA's own process tells the server's
        self.changed: Callable[[], None] | None = None

    def set(self, step: int, at_rest: bool) -> None:
        """The cycles wanted from now on (the loop's: `Monitoring._retune`)."""
        self.step, self.at_rest = step, at_rest
        if self.changed is not None:
            self.changed()

    def wants(self, cycle: int, quiescent: bool) -> bool:
        return cycle % self.step == 0 and (self.at_rest or not quiescent)

    def next_wanted(self, cycle: int, quiescent: bool) -> int | None:
        if quiescent and not self.at_rest:
            return None
        return (cycle // self.step + 1) * self.step


class Monitoring:
    """The monitored items of one interface's variables (see the module). `variables`:
    the interface's variables by node id (shared, filled as machines are made);
    `datavalue`: the DataValue of a variable's value in a snapshot; `per_session` and
    `total`: the caps of items (`OpcUaOptions`)."""

    def __init__(
        self,
        variables: Mapping[Any, Var],
        share: LoopShare,
        datavalue: Callable[[Var, Any, Snapshot], Any],
        per_session: int,
        total: int,
    ) -> None:
        self.variables = variables
        self.share = share
        self.datavalue = datavalue
        self.per_session = per_session
        self.total = total
        #: asyncua's server and loop, once started (`OpcUaInterface._start`)
        self.server: Any = None
        self.loop: asyncio.AbstractEventLoop | None = None
        self._handles: dict[int, Any] = {}  # datachange callback handle -> node id
        #: datachange callback handle -> the rule of its item (`items.py`)
        self._rules: dict[int, ItemRule] = {}
        self._hold: dict[str, Callable[[], None]] = {}
        self._queue: dict[str, deque[Snapshot]] = {}
        self._demands: dict[str, Demand] = {}
        self._watched: dict[str, list[Var]] = {}
        self._drain: asyncio.Task[None] | None = None
        self._woken = False  # a `_wake` is on its way to the loop
        self._closed = False
        #: per machine, what its status shows as `opcua_items` (`counts`)
        self._counts: dict[str, dict[str, int]] = {}

    def counts(self, machine: str) -> dict[str, int]:
        """What `machine`'s status shows as `opcua_items` (its keys fixed, its values
        replaced; each key has one writer): `items`, the monitored items of its
        variables; `samples`, its cycles sampled; `samples_skipped`, those skipped
        while OPC UA's share of notifications was used up (its newest kept);
        `samples_late`, those dropped because the loop was `SAMPLE_QUEUE` behind (the
        cycle's thread's); `notifications`, the values notified to its items."""
        return self._counts.setdefault(
            machine,
            dict.fromkeys(
                ("items", "samples", "samples_skipped", "samples_late", "notifications"), 0
            ),
        )

    def close(self) -> asyncio.Task[None] | None:
        """Stop sampling: the engines' demands given back; the drain under way is
        cancelled and returned (to await)."""
        self._closed = True  # (a `_wake` already on its way starts no new drain)
        for release in self._hold.values():
            release()
        self._hold.clear()
        if self._drain is not None:
            self._drain.cancel()
        return self._drain

    def added(self, node_id: Any, handle: int) -> None:
        """asyncua made a data-change callback (`handle`) of the value of `node_id`."""
        var = self.variables.get(node_id)
        if var is not None:
            self._handles[handle] = node_id
            self._monitor(var, +1)

    def deleted(self, handle: int) -> None:
        """asyncua deletes the data-change callback `handle`."""
        node_id = self._handles.pop(handle, None)
        if node_id is not None:
            var = self.variables[node_id]
            rule = self._rules.pop(handle, None)
            if rule is not None:
                var.count(rule, -1)
            self._monitor(var, -1)

    async def create_items(self, params: Any, create: Any) -> list[Any]:
        """Refuse items past the limits (BadTooManyMonitoredItems), whatever node they
        watch (the server's own nodes too), and items of our variables whose filter
        cannot apply (`items.rule_for`); give each item of our variables its own
        sampling interval in whole GEO cycles and its rule; create the rest."""
        ua = _ua()

        subs = internals.subscriptions(self.server)
        sub = subs.get(params.SubscriptionId)
        session = getattr(sub, "session_id", None)
        in_session = total = 0
        for s in subs.values():
            held = len(internals.monitored_items(s))
            total += held
            in_session += held if s.session_id == session else 0
        keep: list[int] = []
        refused: dict[int, str] = {}
        rules: list[tuple[int, Var, ItemRule]] = []
        for i, item in enumerate(params.ItemsToCreate):
            if in_session >= self.per_session or total >= self.total:
                refused[i] = "BadTooManyMonitoredItems"
                continue
            var = self.variables.get(item.ItemToMonitor.NodeId)
            if var is not None:
                RequestMeter.touch(var.machine)
            if var is not None and item.ItemToMonitor.AttributeId == ua.AttributeIds.Value:
                rule = self._rule(var, item.RequestedParameters, sub)
                if isinstance(rule, str):
                    refused[i] = rule
                    continue
                rules.append((len(keep), var, rule))
            in_session += 1
            total += 1
            keep.append(i)
        created: list[Any] = []
        if keep:
            asked = [params.ItemsToCreate[i] for i in keep]
            sampling = ua.MonitoringMode.Sampling
            # asyncua reports a new item's first value unless it is Disabled: one that
            # only samples is made Disabled, then set to Sampling (Part 4 §5.12.1.3)
            quiet = {k for k, a in enumerate(asked) if a.MonitoringMode == sampling}
            sub_params = ua.CreateMonitoredItemsParameters(
                SubscriptionId=params.SubscriptionId,
                TimestampsToReturn=params.TimestampsToReturn,
                ItemsToCreate=[_disabled(a) if k in quiet else a for k, a in enumerate(asked)],
            )
            created = await create(sub_params)
            made = internals.monitored_items(sub)
            for k in quiet:
                data = made.get(created[k].MonitoredItemId)
                if created[k].StatusCode.is_good() and data is not None:
                    data.mode = sampling
            for k, var, rule in rules:
                if created[k].StatusCode.is_good():
                    self._ruled(var, sub, created[k].MonitoredItemId, rule)
                    created[k].RevisedSamplingInterval = rule.every * _cycle_ms(var)
        return _merged(
            len(params.ItemsToCreate), keep, created, refused, ua.MonitoredItemCreateResult
        )

    async def set_mode(self, params: Any, set_mode: Any) -> list[Any]:
        """SetMonitoringMode; an item of ours that goes from Sampling to Reporting gets
        its variable's value now, against the value last notified to it (asyncua does
        that only coming from Disabled; samples taken meanwhile were not reported)."""
        ua = _ua()

        sub = internals.subscriptions(self.server).get(params.SubscriptionId)
        items = internals.monitored_items(sub)
        was = {mid: items[mid].mode for mid in params.MonitoredItemIds if mid in items}
        results = await set_mode(params)
        if sub is None or params.MonitoringMode != ua.MonitoringMode.Reporting:
            return list(results)
        for mid, mode in was.items():
            data = items.get(mid)
            watched = data.read_value_id if data is not None else None
            if mode != ua.MonitoringMode.Sampling or watched is None or data is None:
                continue
            if watched.NodeId in self.variables and data.callback_handle is not None:
                await internals.trigger_datachange(
                    sub, data.callback_handle, watched.NodeId, watched.AttributeId
                )
        return list(results)

    def modify_items(self, params: Any, modify: Any) -> list[Any]:
        """ModifyMonitoredItems: an item of our variables gets its new interval and
        filter as at its creation, or keeps both when the new filter is refused."""
        ua = _ua()

        sub = internals.subscriptions(self.server).get(params.SubscriptionId)
        items = internals.monitored_items(sub)
        refused: dict[int, str] = {}
        rules: list[tuple[int, Var, ItemRule]] = []
        passed: list[int] = []
        for i, request in enumerate(params.ItemsToModify):
            data = items.get(request.MonitoredItemId)
            if data is None:  # (asyncua would fail the whole request, half applied)
                refused[i] = "BadMonitoredItemIdInvalid"
                continue
            watched: Any = data.read_value_id
            var = self.variables.get(watched.NodeId) if watched is not None else None
            if var is not None and watched.AttributeId == ua.AttributeIds.Value:
                rule = self._rule(var, request.RequestedParameters, sub)
                if isinstance(rule, str):
                    refused[i] = rule
                    continue
                rules.append((len(passed), var, rule))
            passed.append(i)
        done = (
            modify(
                ua.ModifyMonitoredItemsParameters(
                    SubscriptionId=params.SubscriptionId,
                    TimestampsToReturn=params.TimestampsToReturn,
                    ItemsToModify=[params.ItemsToModify[i] for i in passed],
                )
            )
            if passed
            else []
        )
        for k, var, rule in rules:
            if done[k].StatusCode.is_good():
                self._ruled(var, sub, params.ItemsToModify[passed[k]].MonitoredItemId, rule)
                done[k].RevisedSamplingInterval = rule.every * _cycle_ms(var)
        return _merged(
            len(params.ItemsToModify), passed, done, refused, ua.MonitoredItemModifyResult
        )

    def _rule(self, var: Var, asked: Any, sub: Any) -> ItemRule | str:
        """The rule of an item of `var` with the MonitoringParameters `asked`, or the
        status that refuses its filter."""
        publishing = float(sub.data.RevisedPublishingInterval) if sub is not None else 0.0
        every = cycles_of(float(asked.SamplingInterval), publishing, _cycle_ms(var))
        flt = asked.Filter
        if _plain(flt):
            return ItemRule(every)
        if not isinstance(flt, _change_filter()):
            return "BadFilterNotAllowed"  # (an event or aggregate filter on a value)
        return rule_for(
            every,
            int(flt.Trigger),
            int(flt.DeadbandType),
            float(flt.DeadbandValue),
            numeric=var.numeric,
            eu_range=var.eu_range,
        )

    def _ruled(self, var: Var, sub: Any, mid: int, rule: ItemRule) -> None:
        """Give the item `mid` of `sub` its rule (replacing the one it had)."""
        data = internals.monitored_items(sub).get(mid)
        handle = data.callback_handle if data is not None else None
        if handle is None or self._handles.get(handle) != var.node_id:
            return
        old = self._rules.get(handle)
        if old is not None:
            var.count(old, -1)
        self._rules[handle] = rule
        var.count(rule, +1)
        self._retune(var.machine)

    def _monitor(self, var: Var, delta: int) -> None:
        """Count the monitored items of `var`; the first one of a machine starts
        sampling it every cycle, the last one's removal stops that."""
        var.monitors = max(0, var.monitors + delta)
        items = sum(v.monitors for v in self.variables.values() if v.machine == var.machine)
        self.counts(var.machine)["items"] = items
        watched = items > 0
        if watched and var.machine not in self._hold:
            self._hold[var.machine] = self._sampling(var.machine, var.service)
        elif not watched and var.machine in self._hold:
            self._hold.pop(var.machine)()
        self._retune(var.machine)

    def _retune(self, machine: str) -> None:
        """The machine's monitored variables (sampled by `_drain_queue`) and the cycles
        they need (`Demand`)."""
        watched = [v for v in self.variables.values() if v.machine == machine and v.monitors]
        self._watched[machine] = [v for v in watched if v.readable]
        demand = self._demands.get(machine)
        if demand is None:
            return
        # (an item notified of every sample's new timestamp needs the cycles at rest too)
        demand.set(
            math.gcd(*(v.every for v in watched)) if watched else 1,
            any(v.at_rest or v.stamped for v in watched),
        )

    def _sampling(self, machine: str, service: OpcUaService) -> Callable[[], None]:
        """Every cycle's snapshot of `machine`, handed to the loop (`_drain_queue`)."""
        loop = self.loop
        assert loop is not None
        queue = self._queue.setdefault(machine, deque())
        counts = self.counts(machine)

        def on_cycle(snap: Snapshot) -> None:  # the cycle's thread: hand over, return
            # (deque appends and pops are atomic; the loop is woken once for all the
            # snapshots that arrive until it drains them, not once per cycle)
            queue.append(snap)
            if len(queue) > SAMPLE_QUEUE:
                with contextlib.suppress(IndexError):
                    queue.popleft()
                    counts["samples_late"] += 1
            if not self._woken:
                self._woken = True
                with contextlib.suppress(RuntimeError):  # the loop is closed: nobody listens
                    loop.call_soon_threadsafe(self._wake)

        wanted = self._demands[machine] = Demand()
        release = service.demand_cycles(wanted)  # the exact engine publishes only those
        # `subscribe` hands over the snapshots themselves, with their time stamps
        unsubscribe = service.subscribe(on_cycle)

        def stop() -> None:
            unsubscribe()
            release()
            self._demands.pop(machine, None)
            queue.clear()

        return stop

    def _wake(self) -> None:
        self._woken = False  # (before draining: a snapshot arriving now wakes again)
        if self._closed:
            return
        if self._drain is None or self._drain.done():
            self._drain = asyncio.ensure_future(self._drain_queue())

    async def _drain_queue(self) -> None:
        """Each sampled cycle's changed values, one DataValue each, to the monitored
        items of their variables (`_notify`), in cycle order, each snapshot followed by
        the loop's other work (the cycle's thread keeps adding snapshots: draining them
        without a pause could hold the loop for good)."""
        share = self.share
        while True:
            wait = share.wait()
            if wait > 0.0:  # OPC UA's share is used up: sample less often
                await asyncio.sleep(wait)
                self._coalesce()
            batch = [(m, s) for m, q in self._queue.items() for s in _taken(q)]
            if not batch:
                return
            for machine, snap in batch:
                began = time.thread_time()
                await self._notify_snapshot(machine, snap)
                share.charge(time.thread_time() - began)
                await asyncio.sleep(0)

    def _coalesce(self) -> None:
        """Keep only the newest snapshot of each machine (`samples_skipped` counts the
        others; `samples_late` is the cycle's thread's)."""
        for machine, queue in self._queue.items():
            counts = self.counts(machine)
            while len(queue) > 1:
                with contextlib.suppress(IndexError):
                    queue.popleft()
                    counts["samples_skipped"] += 1

    async def _notify_snapshot(self, machine: str, snap: Snapshot) -> None:
        """The values of one sampled cycle to the monitored items that sample it: at
        each sampling interval that falls on this cycle, a value that differs from the
        one sampled last at that interval (or any value, for an item notified of every
        sample) goes to its items (`_notify`), one DataValue shared by them."""
        counts = self.counts(machine)
        counts["samples"] += 1
        for var in self._watched.get(machine, ()):
            if snap.cycle % var.every:
                continue
            value = var.value(snap)
            due = set()
            for every in var.rates:
                if snap.cycle % every:
                    continue
                if var.stamped or not same(var.lasts.get(every, _NONE), value):
                    var.lasts[every] = value
                    due.add(every)
            if due:
                counts["notifications"] += 1
                await self._notify(var, self.datavalue(var, value, snap), due)

    async def _notify(self, var: Var, dv: Any, due: set[int]) -> None:
        """`dv` to the monitored items of `var` that sample at an interval in `due` and
        whose rule passes it (`ItemRule.notifies`, against the value last notified to
        the item), as asyncua's `datachange_callback` does after a write of the node,
        without its deep copy of the value per item (most of its cost: `dv` is made for
        this and never changed): the item's last value, queued for the item's
        subscription with the item's queue size."""
        ua = _ua()

        new = _sample(dv)
        callbacks = internals.callbacks_of(var.attval)
        for i, (handle, callback) in enumerate(callbacks):
            if i and i % NOTIFY_SLICE == 0:  # the loop's other work in between
                await asyncio.sleep(0)
            rule = self._rules.get(handle)
            if rule is None or rule.every not in due:
                continue  # (not due; or an item being made or deleted meanwhile)
            target = internals.item_of(callback, handle)
            if target is None:
                continue
            item = target.item
            if item.mode != ua.MonitoringMode.Reporting:
                continue  # (Sampling: sampled, not reported; Part 4 §5.12.1.3)
            values = item.mvalue
            old = values.current_dvalue
            if not rule.notifies(None if old is None else _sample(old), new):
                continue
            values.old_dvalue, values.current_dvalue = old, dv
            note = ua.MonitoredItemNotification(ClientHandle=item.client_handle, Value=dv)
            await internals.enqueue(target, note)


#: no value sampled yet (at an interval; `Var.lasts`)
_NONE = object()


def _taken(queue: deque[Snapshot]) -> list[Snapshot]:
    """The snapshots in `queue` now, taken out (the cycle's thread may drop the oldest
    meanwhile: `SAMPLE_QUEUE`)."""
    out = []
    for _ in range(len(queue)):
        try:
            out.append(queue.popleft())
        except IndexError:
            break
    return out


def _cycle_ms(var: Var) -> float:
    return var.service.info.cycle_s * 1000.0


def _sample(dv: Any) -> Sample:
    """What `items.ItemRule` compares of a DataValue."""
    value = dv.Value.Value if dv.Value is not None else None
    stamp = dv.SourceTimestamp or FILETIME_EPOCH.replace(tzinfo=None)
    return Sample(dv.StatusCode.value, value, stamp.replace(tzinfo=None))


def _merged(
    count: int, passed: list[int], done: list[Any], refused: dict[int, str], result: Any
) -> list[Any]:
    """The results of a request's items in their order: asyncua's for those passed to
    it, a `result` with the status named in `refused` for the others."""
    ua = _ua()

    out: list[Any] = [None] * count
    for k, i in enumerate(passed):
        out[i] = done[k]
    for i, status in refused.items():
        out[i] = result(StatusCode=ua.StatusCode(getattr(ua.StatusCodes, status)))
    return out


def _disabled(request: Any) -> Any:
    """A MonitoredItemCreateRequest as it is, but Disabled."""
    ua = _ua()

    return ua.MonitoredItemCreateRequest(
        ItemToMonitor=request.ItemToMonitor,
        MonitoringMode=ua.MonitoringMode.Disabled,
        RequestedParameters=request.RequestedParameters,
    )


def _change_filter() -> Any:
    """The DataChangeFilter class that asyncua decodes (`ua.DataChangeFilter` is a
    subclass of it that the decoder does not make)."""
    from asyncua.ua import uaprotocol_auto

    return uaprotocol_auto.DataChangeFilter


def _plain(flt: Any) -> bool:
    """No filter (None, or an empty ExtensionObject as asyncua's client sends), or a
    DataChangeFilter that asks for the default: a notification when the status or the
    value changes, without a deadband (OPC UA 1.05 Part 4 §7.22.2)."""
    if not flt:
        return True
    ua = _ua()

    return (
        isinstance(flt, _change_filter())
        and flt.Trigger == ua.DataChangeTrigger.StatusValue
        and flt.DeadbandType == ua.DeadbandType.None_
    )
