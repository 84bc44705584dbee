"""A print's flow, gathered as it runs, in memory that does not grow with it.

The adapter feeds one `Sample` every fraction of a second (what klippy's
objects say at that moment) and the recorder keeps:

- the series over time in at most `max_bins` bins of equal width; when the
  print outlasts them, neighbours merge pairwise and the width doubles. Each
  bin keeps count, sum, min and max per channel, so a mean is exact and a
  spike survives any amount of merging;
- per layer: filament commanded and under-extruded (commanded minus
  measured, where grip is below 1 by more than the sensor's noise);
- spans: where and why the limiter slowed the print (and the time it cost),
  where the sensor was faulted or no data came (the time lost), which profile
  and working point were in force; each list bounded, its closest
  neighbours merged when full;
- a few events (the print paused or resumed, a fault starting or clearing),
  bounded too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

# The series kept per bin, in this order.
CHANNELS = ("commanded_flow", "measured_flow", "grip", "temp", "target",
            "planned_temp", "cap")
# How often the host samples klippy's objects for the report (the Moonraker
# component's period, and the bench's)
SAMPLE_PERIOD_S = 0.25
DEFAULT_MAX_BINS = 512
DEFAULT_BIN_WIDTH_S = 1.0
# A grip window of 1.25 mm is ~128 counts: one count of quantisation (0.8 %)
# and the reading noise of two reads (0.34 counts RMS each, 3 sigma ~1.1 %)
# make a grip of 0.98 indistinguishable from 1.
DEFAULT_GRIP_NOISE = 0.02
DEFAULT_FILAMENT_DIAMETER_MM = 1.75
# A pause between samples longer than this is a gap (klippy away, Moonraker
# busy): its time is counted lost, nothing is integrated over it.
MAX_SAMPLE_GAP_S = 5.0
MAX_SPANS = 200
# Z above the layer's that starts a new one (without the slicer's numbers)
LAYER_Z_STEP_MM = 0.01
MAX_EVENTS = 100
# Slowdowns closer than this are one span (the limiter acts window by window).
SPAN_JOIN_S = 2.0
# How a job ended, in Moonraker's history words; anything else is unfinished.
FINISHED = "completed"


@dataclass(frozen=True)
class Sample:
    """What klippy's objects say at one moment of a print."""

    time_s: float                                  # since the job started
    print_state: str = "printing"                  # print_stats.state
    commanded_flow_mm3_s: Optional[float] = None
    measured_flow_mm3_s: Optional[float] = None
    grip: Optional[float] = None
    temp_c: Optional[float] = None                 # the nozzle
    target_c: Optional[float] = None               # the heater's target
    planned_temp_c: Optional[float] = None         # autotemp's target
    cap_mm3_s: Optional[float] = None
    cap_reason: str = "none"
    slowed_time_s: Optional[float] = None          # the limiter's running total
    sensor: bool = True                            # a flow sensor reports at all
    sensor_fault: Optional[str] = None
    layer: Optional[int] = None
    z_mm: Optional[float] = None
    profile: Optional[str] = None
    working_point: Optional[float] = None

    def channel_values(self) -> Tuple[Optional[float], ...]:
        return (self.commanded_flow_mm3_s, self.measured_flow_mm3_s, self.grip,
                self.temp_c, self.target_c, self.planned_temp_c, self.cap_mm3_s)


class Bins:
    """Equal-width time bins, at most `max_bins`, merged pairwise when full.

    A bin is None (no sample fell in it) or, per channel, None (no value) or
    [count, sum, min, max]."""

    def __init__(self, max_bins: int = DEFAULT_MAX_BINS,
                 width_s: float = DEFAULT_BIN_WIDTH_S) -> None:
        if max_bins < 2 or max_bins % 2:
            raise ValueError("max_bins must be even and at least 2")
        self.max_bins = max_bins
        self.width_s = width_s
        self.rows: List[Optional[List[Optional[List[float]]]]] = []

    def add(self, time_s: float, values: Sequence[Optional[float]]) -> None:
        index = int(max(0.0, time_s) // self.width_s)
        while index >= self.max_bins:
            self._halve()
            index = int(max(0.0, time_s) // self.width_s)
        if index >= len(self.rows):
            self.rows.extend([None] * (index + 1 - len(self.rows)))
        row = self.rows[index]
        if row is None:
            row = self.rows[index] = [None] * len(values)
        for k, value in enumerate(values):
            if value is None or not math.isfinite(value):
                continue
            cell = row[k]
            if cell is None:
                row[k] = [1.0, value, value, value]
            else:
                cell[0] += 1
                cell[1] += value
                if value < cell[2]:
                    cell[2] = value
                if value > cell[3]:
                    cell[3] = value

    def _halve(self) -> None:
        rows = self.rows + [None] * (len(self.rows) % 2)
        self.rows = [merge_rows(rows[i], rows[i + 1])
                     for i in range(0, len(rows), 2)]
        self.width_s *= 2

    def series(self, channel: str, stat: str = "mean"
               ) -> List[Tuple[float, Optional[float]]]:
        """(bin centre s, the channel's mean/min/max or None) per bin."""
        k = CHANNELS.index(channel)
        out = []
        for i, row in enumerate(self.rows):
            cell = None if row is None else row[k]
            t = (i + 0.5) * self.width_s
            if cell is None:
                out.append((t, None))
            elif stat == "mean":
                out.append((t, cell[1] / cell[0]))
            else:
                out.append((t, cell[2] if stat == "min" else cell[3]))
        return out

    def extreme(self, channel: str, stat: str) -> Optional[float]:
        """The channel's min or max over the whole print."""
        values = [v for _, v in self.series(channel, stat) if v is not None]
        if not values:
            return None
        return min(values) if stat == "min" else max(values)


def merge_rows(a, b):
    if a is None or b is None:
        return a if b is None else b
    return [merge_cells(x, y) for x, y in zip(a, b)]


def merge_cells(a, b):
    if a is None or b is None:
        return a if b is None else b
    return [a[0] + b[0], a[1] + b[1], min(a[2], b[2]), max(a[3], b[3])]


@dataclass
class Span:
    """A stretch of the print: a limiter slowdown (kind = its reason), a
    sensor fault (kind = the fault) or a gap in the data, or a profile in force."""

    kind: str
    start_s: float
    end_s: float
    cost_s: float = 0.0          # time it added (slowdowns) or lost (faults)
    layer: Optional[int] = None  # where it started
    working_point: Optional[float] = None  # profiles only


class Spans:
    """A bounded list of spans: the closest neighbours merge when it is full."""

    def __init__(self, max_spans: int = MAX_SPANS) -> None:
        self.max_spans = max_spans
        self.items: List[Span] = []

    def extend(self, kind: str, start_s: float, end_s: float, cost_s: float,
               layer: Optional[int], join_s: float = SPAN_JOIN_S) -> None:
        last = self.items[-1] if self.items else None
        if last is not None and last.kind == kind and start_s - last.end_s <= join_s:
            last.end_s = max(last.end_s, end_s)
            last.cost_s += cost_s
            return
        self.items.append(Span(kind, start_s, end_s, cost_s, layer))
        if len(self.items) > self.max_spans:
            self._merge_closest()

    def _merge_closest(self) -> None:
        gaps = [(self.items[i + 1].start_s - self.items[i].end_s, i)
                for i in range(len(self.items) - 1)]
        _, i = min(gaps)
        a, b = self.items[i], self.items[i + 1]
        kind = a.kind if a.kind == b.kind else " + ".join(
            sorted(set(a.kind.split(" + ")) | set(b.kind.split(" + "))))
        self.items[i:i + 2] = [Span(kind, a.start_s, b.end_s, a.cost_s + b.cost_s,
                                    a.layer, a.working_point)]


@dataclass
class Layer:
    """One layer's filament: commanded, and under-extruded where grip was low."""

    layer: int
    z_mm: Optional[float] = None
    time_s: float = 0.0
    commanded_mm: float = 0.0
    under_mm: float = 0.0


@dataclass
class Event:
    time_s: float
    text: str


@dataclass
class Job:
    """What the host knows of the job (Moonraker's history)."""

    job_id: Optional[str] = None
    filename: Optional[str] = None
    started_at: Optional[float] = None   # wall clock, s since the epoch
    sensor_name: Optional[str] = None
    state: Optional[str] = None          # how it ended: completed, cancelled, ...
    end_s: Optional[float] = None


@dataclass
class Recorder:
    """A print's flow report, gathered as it runs."""

    job: Job = field(default_factory=Job)
    filament_diameter_mm: float = DEFAULT_FILAMENT_DIAMETER_MM
    grip_noise: float = DEFAULT_GRIP_NOISE
    bins: Bins = field(default_factory=Bins)
    layers: Dict[int, Layer] = field(default_factory=dict)
    slowdowns: Spans = field(default_factory=Spans)
    faults: Spans = field(default_factory=Spans)
    profiles: Spans = field(default_factory=Spans)
    events: List[Event] = field(default_factory=list)
    events_dropped: int = 0
    samples: int = 0
    sensor_samples: int = 0      # samples with a sensor that was not faulted
    faulted_samples: int = 0
    planned_samples: int = 0     # samples with an autotemp target
    commanded_mm: float = 0.0
    under_mm: float = 0.0
    last: Optional[Sample] = None
    current_layer: Optional[Layer] = None
    z_layer: Optional[int] = None       # the layer counted from Z, 1 first
    z_layer_mm: Optional[float] = None

    @property
    def filament_area_mm2(self) -> float:
        return math.pi / 4 * self.filament_diameter_mm ** 2

    # --- feeding ----------------------------------------------------------------
    def sample(self, s: Sample) -> None:
        last = self.last
        if last is not None and s.time_s < last.time_s:
            return  # out of order: the clock is the adapter's; never integrate back
        self.samples += 1
        self.bins.add(s.time_s, s.channel_values())
        dt = 0.0 if last is None else s.time_s - last.time_s
        if dt > MAX_SAMPLE_GAP_S:
            self.faults.extend("no data", last.time_s, s.time_s, dt, last.layer,
                               join_s=0.0)
            dt = 0.0
        self._note_changes(last, s)
        if dt > 0 and last is not None:
            # the interval takes the state at its start: what was in force then
            self._integrate(last, s, dt, self.current_layer)
        self.current_layer = self._layer(s)
        if s.sensor and s.sensor_fault is None:
            self.sensor_samples += 1
        if s.sensor_fault is not None:
            self.faulted_samples += 1
        if s.planned_temp_c is not None:
            self.planned_samples += 1
        self.last = s

    def _layer(self, s: Sample) -> Optional[Layer]:
        key = s.layer if s.layer is not None else self._layer_from_z(s)
        if key is None:
            return None
        layer = self.layers.get(key)
        if layer is None:
            layer = self.layers[key] = Layer(key, s.z_mm)
        elif layer.z_mm is None:
            layer.z_mm = s.z_mm
        return layer

    def _layer_from_z(self, s: Sample) -> Optional[int]:
        """Without the slicer's layer numbers: a new layer where the nozzle
        extrudes higher than it did (a Z hop travels, it does not extrude)."""
        if s.z_mm is None:
            return None
        extruding = (s.commanded_flow_mm3_s or 0.0) > 0
        if extruding and (self.z_layer_mm is None
                          or s.z_mm > self.z_layer_mm + LAYER_Z_STEP_MM):
            self.z_layer = 1 if self.z_layer is None else self.z_layer + 1
            self.z_layer_mm = s.z_mm
        return self.z_layer

    def _integrate(self, last: Sample, s: Sample, dt: float,
                   layer: Optional[Layer]) -> None:
        flow = last.commanded_flow_mm3_s
        commanded_mm = 0.0 if flow is None or flow <= 0 else \
            flow * dt / self.filament_area_mm2
        under = 0.0
        judged = last.grip is not None and last.sensor_fault is None
        if judged and last.grip < 1.0 - self.grip_noise:
            under = commanded_mm * (1.0 - max(0.0, last.grip))
        self.commanded_mm += commanded_mm
        self.under_mm += under
        if layer is not None:
            layer.time_s += dt
            layer.commanded_mm += commanded_mm
            layer.under_mm += under
        layer_no = None if layer is None else layer.layer
        cost = _slowed(last.slowed_time_s, s.slowed_time_s)
        if cost > 0:
            reason = s.cap_reason if s.cap_reason != "none" else last.cap_reason
            self.slowdowns.extend(reason, last.time_s, s.time_s, cost, layer_no)
        if last.sensor_fault is not None:
            self.faults.extend(last.sensor_fault, last.time_s, s.time_s, dt,
                               layer_no, join_s=0.0)

    def _note_changes(self, last: Optional[Sample], s: Sample) -> None:
        before = last or Sample(s.time_s, print_state="", sensor=s.sensor)
        if s.print_state != before.print_state and last is not None:
            self.event(s.time_s, f"print {s.print_state}")
        if s.sensor_fault != before.sensor_fault:
            self.event(s.time_s, "sensor fault cleared" if s.sensor_fault is None
                       else f"sensor fault '{s.sensor_fault}'")
        if s.profile is not None:
            items = self.profiles.items
            if (not items or items[-1].kind != s.profile
                    or items[-1].working_point != s.working_point):
                self.profiles.items.append(Span(s.profile, s.time_s, s.time_s,
                                                layer=s.layer,
                                                working_point=s.working_point))
                del self.profiles.items[:-MAX_SPANS]
            else:
                items[-1].end_s = s.time_s

    def event(self, time_s: float, text: str) -> None:
        if len(self.events) >= MAX_EVENTS:
            self.events_dropped += 1
            return
        self.events.append(Event(time_s, text))

    def finish(self, state: str, time_s: Optional[float] = None) -> None:
        """The job ended (Moonraker's history status: completed, cancelled,
        error, klippy_shutdown, klippy_disconnect, ...)."""
        self.job.state = state
        end = time_s if time_s is not None else (
            self.last.time_s if self.last is not None else 0.0)
        self.job.end_s = end
        if self.last is not None and self.last.sensor_fault is not None \
                and end > self.last.time_s:
            self.faults.extend(self.last.sensor_fault, self.last.time_s, end,
                               end - self.last.time_s, self.last.layer, join_s=0.0)

    # --- what it says -----------------------------------------------------------
    def duration_s(self) -> float:
        if self.job.end_s is not None:
            return self.job.end_s
        return 0.0 if self.last is None else self.last.time_s

    def slowdown_by_reason(self) -> Dict[str, float]:
        out: Dict[str, float] = {}
        for span in self.slowdowns.items:
            out[span.kind] = out.get(span.kind, 0.0) + span.cost_s
        return out

    def lost_s(self) -> float:
        return sum(span.cost_s for span in self.faults.items)

    def lacks(self) -> List[str]:
        """What this report cannot tell, one sentence each."""
        out = []
        state = self.job.state
        if state is None:
            out.append("the print had not ended when this report was made")
        elif state != FINISHED:
            out.append(f"the print did not complete ({state} after "
                       f"{duration_text(self.duration_s())})")
        if not self.job.filename:
            out.append("the job has no file name")
        if self.samples == 0:
            out.append("no data was recorded")
            return out
        sensed = self.sensor_samples + self.faulted_samples
        if sensed == 0:
            out.append("no flow sensor data: measured flow, grip and "
                       "under-extrusion are unknown")
        elif self.sensor_samples == 0:
            out.append("the flow sensor was faulted for the whole print: grip "
                       "and under-extrusion are unknown")
        if self.planned_samples == 0:
            out.append("autotemp planned no temperature for this print")
        if not self.layers:
            out.append("no layer information: under-extrusion is not split by "
                       "layer")
        gaps = [s for s in self.faults.items if s.kind == "no data"]
        if gaps:
            out.append(f"no data for {duration_text(sum(s.cost_s for s in gaps))} "
                       f"in {len(gaps)} gap(s) (klippy restarting or away)")
        return out


def _slowed(before: Optional[float], after: Optional[float]) -> float:
    """Time the limiter added between two readings of its running total (a
    total that fell is a restarted klippy: nothing is known of that interval)."""
    if before is None or after is None or after < before:
        return 0.0
    return after - before


def duration_text(seconds: float) -> str:
    seconds = int(round(seconds))
    if seconds < 60:
        return f"{seconds} s"
    minutes, seconds = divmod(seconds, 60)
    if minutes < 60:
        return f"{minutes} min {seconds:02d} s"
    hours, minutes = divmod(minutes, 60)
    return f"{hours} h {minutes:02d} min"


# --- klippy's objects, as Moonraker's subscription holds them -----------------

Tools = Dict[str, Dict[str, Optional[str]]]


def one_tool(sensor_name: Optional[str]) -> Tools:
    """The tools of a printer with one extruder: its sensor (by name, or
    none), `flowrate_limiter` and `autotemp`."""
    return {"extruder": {
        "sensor": None if sensor_name is None else f"flow_sensor {sensor_name}",
        "limiter": "flowrate_limiter", "autotemp": "autotemp"}}


def status_objects(tools: Tools) -> Dict[str, Optional[List[str]]]:
    """The klippy objects (and fields) a sample is read from, for every
    tool (control.tools.tool_objects names each tool's)."""
    objects: Dict[str, Optional[List[str]]] = {
        "print_stats": ["state", "filename", "info"],
        "toolhead": ["position", "extruder"],
        "flowloop": ["profiles"],
    }
    for extruder, own in tools.items():
        objects[extruder] = ["temperature", "target"]
        if own.get("sensor"):
            objects[own["sensor"]] = ["grip", "measured_flow", "commanded_flow",
                                      "fault"]
        if own.get("limiter"):
            objects[own["limiter"]] = ["cap", "reason", "slowed_time"]
        if own.get("autotemp"):
            objects[own["autotemp"]] = ["active", "target", "profile",
                                        "working_point"]
    return objects


def sample_from_status(time_s: float, status: Dict[str, dict], tools: Tools
                       ) -> Sample:
    """One sample from klippy's objects, of the tool that prints now (the
    toolhead's extruder: a toolchanger's report follows its tool changes);
    missing objects read as unknown."""
    def of(name: Optional[str]) -> dict:
        return (status.get(name) or {}) if name else {}
    ps = of("print_stats")
    info = ps.get("info") or {}
    toolhead = of("toolhead")
    position = toolhead.get("position") or []
    extruder = toolhead.get("extruder") or "extruder"
    own = tools.get(extruder) or {}
    heater = of(extruder)
    limiter = of(own.get("limiter"))
    auto = of(own.get("autotemp"))
    sensor = of(own.get("sensor"))
    active = (of("flowloop").get("profiles") or {}).get(extruder) or {}
    return Sample(
        time_s=time_s,
        print_state=ps.get("state") or "printing",
        commanded_flow_mm3_s=sensor.get("commanded_flow"),
        measured_flow_mm3_s=sensor.get("measured_flow"),
        grip=sensor.get("grip"),
        temp_c=heater.get("temperature"),
        target_c=heater.get("target"),
        planned_temp_c=auto.get("target") if auto.get("active") else None,
        cap_mm3_s=limiter.get("cap"),
        cap_reason=limiter.get("reason") or "none",
        slowed_time_s=limiter.get("slowed_time"),
        sensor=bool(sensor),
        sensor_fault=sensor.get("fault"),
        layer=info.get("current_layer"),
        z_mm=position[2] if len(position) > 2 else None,
        profile=auto.get("profile") or active.get("name"),
        working_point=(auto.get("working_point") if auto.get("profile")
                       else active.get("working_point")),
    )
