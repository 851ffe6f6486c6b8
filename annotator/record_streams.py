"""A dropped stream in `dsr-bench capture` (`annotator.record`; docs/annotator.md, "Recording a session"): what has
arrived of each camera's colour and depth stream, and the checks that tell a stream has stopped delivering frames.

Three checks, each against `timeout_frames` (the `--timeout-frames` option; frame periods of the stream's rate):

- the frame numbers: a jump of more than timeout_frames (a stall the camera came back from) is a dropped stream, a
  number going back is a restarted camera; smaller jumps are frames lost, counted;
- the frames' clock, within a camera: the camera's other stream goes on for more than timeout_frames frames and
  more than timeout_frames periods past this stream's last frame. Both counts, because the two streams are delivered
  by two threads (a recording standing in plays faster than real time: one may run a few frames ahead);
- the host's clock (connected cameras only): no frame for timeout_frames periods, or none within START_TIMEOUT_S of
  starting.
"""

from __future__ import annotations

from dataclasses import dataclass

#: A connected camera's first frame must come within this many seconds of starting (auto-exposure settles first).
START_TIMEOUT_S = 10.0
KINDS = {"color": "colour", "depth": "depth"}


@dataclass
class Stream:
    """What has arrived of one camera's colour or depth stream (numbers, timestamps s on the frames' clock, arrival
    s on the host's clock), frames lost, and `behind`: frames of the camera's other stream past this one's
    deadline."""

    fps: int
    count: int = 0
    first_number: int | None = None
    first_stamp: float | None = None
    last_number: int | None = None
    last_stamp: float | None = None
    last_arrival: float | None = None
    lost: int = 0
    gaps: int = 0
    behind: int = 0


def frame_problem(camera: str, streams: dict[str, Stream], kind: str, number: int, stamp: float, arrival: float,
                  timeout_frames: int) -> str | None:
    """Record a frame of `camera`'s `kind` stream ("color", "depth") in `streams` ({kind: Stream}, the camera's);
    the dropped stream it reveals (one line), or None."""
    what, stream = KINDS[kind], streams[kind]
    if stream.last_number is not None:
        jump = number - stream.last_number
        if jump <= 0:
            return (f"the {camera} {what} stream's frame numbers went back from {stream.last_number} to {number} (the "
                    "camera restarted)")
        if jump - 1 > timeout_frames:
            return (f"the {camera} {what} stream dropped: its frame numbers jump from {stream.last_number} to {number} "
                    f"({jump - 1} frames lost, over --timeout-frames {timeout_frames})")
        stream.lost += jump - 1
        stream.gaps += jump > 1
    else:
        stream.first_number, stream.first_stamp = number, stamp
    stream.count += 1
    stream.last_number, stream.last_stamp, stream.last_arrival, stream.behind = number, stamp, arrival, 0
    for other_kind, other in streams.items():
        if other is stream:
            continue
        firsts = [s.first_stamp for s in streams.values() if s.first_stamp is not None]
        reference = other.last_stamp if other.last_stamp is not None else min(firsts)
        if stamp > reference + timeout_frames / other.fps:
            other.behind += 1
            if other.behind > timeout_frames:
                last = f"frame {other.last_number} at {other.last_stamp:.3f} s" if other.count else "no frame"
                return (f"the {camera} {KINDS[other_kind]} stream stopped delivering frames (last {last}; the {what} "
                        f"stream went on {stamp - reference:.1f} s, over --timeout-frames {timeout_frames})")
    return None


def clock_problem(cameras: dict[str, dict[str, Stream]], now: float, started: float, timeout_frames: int
                  ) -> str | None:
    """The first stream of connected cameras silent for timeout_frames periods at `now` (s, host clock), or with no
    frame START_TIMEOUT_S after `started`; None when all deliver."""
    for name, streams in cameras.items():
        for kind, stream in streams.items():
            if stream.last_arrival is None:
                if now - started > START_TIMEOUT_S:
                    return (f"the {name} {KINDS[kind]} stream delivered no frame within {START_TIMEOUT_S:g} s of "
                            "starting (check the camera's USB 3 cable and port)")
            elif now - stream.last_arrival > timeout_frames / stream.fps:
                return (f"the {name} {KINDS[kind]} stream stopped delivering frames (none for "
                        f"{now - stream.last_arrival:.1f} s after frame {stream.last_number}, over --timeout-frames "
                        f"{timeout_frames} at {stream.fps} fps; check the camera's USB cable)")
    return None
