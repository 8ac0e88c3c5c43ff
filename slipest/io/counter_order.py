"""A wheel's frames put back in counter order when a link swaps a few of them (pure computation).

Frames of one CAN identifier can leave a node out of order: a controller with
several transmit mailboxes sends them by identifier and mailbox number, not
by age (bxCAN without transmit-FIFO priority), and a logger that merges
buffers can write a frame a few frames late.  Taken in arrival order, the
frame that came early makes the stream count the late one lost (a NaN sample
in its place), and the late one is then dropped as out of order: a sample
lost whose data came.

:class:`CounterOrder` sits in front of the stream's rules
(:class:`~slipest.io.device_stream.WheelStream`) and hands frames on in
arrival order while each one's counter is the next one, at no cost beyond a
comparison.  A frame up to ``window`` counter steps ahead of the next one is
held; when the missing frame comes it is handed on first, then the held ones
in counter order (``reordered`` counts the frames so put back).  When
``window`` frames are held, or a frame comes further ahead, the missing one
is given up: the held frames go on in counter order, and the stream finds the
missing one lost, as without this stage.  A frame behind the next one (a
duplicate, a frame later than the window, a device that started counting
again) goes on at once, after the held ones; when the frame after it follows
it by one counter step, the counter started again and the stage follows it.
A second frame with the counter of one held is dropped (``duplicates``).

So frames that come in order are handed on unchanged and at once, the frames
of a link that swaps frames come out in counter order, and a lost frame
delays the ``window`` frames after it (``window`` sample periods).  The
output depends only on the frames and their order, not on how they are split
between calls.
"""

from __future__ import annotations

__all__ = ["CounterOrder"]


class CounterOrder:
    """Frames of one wheel put back in counter order within ``window`` frames (see the module docstring).

    ``modulus``: the counter's range (256 on CAN); ``window``: most frames held waiting for a missing one
    (1 to a quarter of ``modulus``).  ``reordered`` and ``duplicates``: frames put back, frames dropped.
    """

    def __init__(self, modulus: int, window: int):
        modulus, window = int(modulus), int(window)
        if modulus < 8 or not 1 <= window <= modulus // 4:
            raise ValueError(f"a counter range of at least 8 and a window of 1 to a quarter of it expected, got "
                             f"{modulus} and {window}")
        self.modulus = modulus
        self.window = window
        self.reordered = 0
        self.duplicates = 0
        self._next: int | None = None  # the counter of the frame expected next
        self._after_behind: int | None = None  # the counter following a frame that came behind the next one
        self._held: dict[int, tuple] = {}  # counter -> the frame's other fields

    def __len__(self) -> int:
        """Frames held."""
        return len(self._held)

    def order(self, seqs: list, fields: tuple[list, ...]) -> tuple[list, tuple[list, ...]]:
        """Frames in arrival order, as their counters ``seqs`` (ints) and their other fields (lists as long),
        -> the frames to take now, in the order to take them (the same lists when all came in order)."""
        m = self.modulus
        nxt = self._next
        i = 0
        if nxt is not None and not self._held:  # the usual case: each frame the next one
            n = len(seqs)
            if n >= 16:  # compared as lists, in C
                expected = (list(range(nxt, m)) + list(range(m)) * (n // m + 1))[:n]
                if seqs == expected:
                    self._next = (nxt + n) % m
                    self._after_behind = None
                    return seqs, fields
            for s in seqs:
                if s != nxt:
                    break
                nxt = nxt + 1 if nxt + 1 < m else 0
                i += 1
            self._next = nxt
            if i:  # a frame in order: no longer right after one that came behind
                self._after_behind = None
            if i == len(seqs):
                return seqs, fields
        out_seqs = seqs[:i]
        out_fields = tuple(f[:i] for f in fields)
        for k in range(i, len(seqs)):
            self._one(int(seqs[k]), tuple(f[k] for f in fields), out_seqs, out_fields)
        return out_seqs, out_fields

    def flush(self) -> tuple[list, tuple[list, ...]]:
        """The held frames, in counter order (end of stream): ``(seqs, fields)``, fields as a tuple of lists."""
        out_seqs: list = []
        out_fields: tuple = ()
        if self._held:
            out_fields = tuple([] for _ in next(iter(self._held.values())))
            self._release(out_seqs, out_fields)
        return out_seqs, out_fields

    def _one(self, s: int, rest: tuple, out_seqs: list, out_fields: tuple) -> None:
        m = self.modulus
        if self._next is None:
            self._emit(s, rest, out_seqs, out_fields)
            return
        if s == self._after_behind and s != self._next:  # two frames in a row behind: the counter started again
            self._release(out_seqs, out_fields)
            self._emit(s, rest, out_seqs, out_fields)
            return
        self._after_behind = None
        ahead = (s - self._next) % m
        if ahead == 0:
            if self._held:
                self.reordered += 1
            self._emit(s, rest, out_seqs, out_fields)
            while self._next in self._held:
                s = self._next
                self._emit(s, self._held.pop(s), out_seqs, out_fields)
        elif ahead <= self.window:
            if s in self._held:
                self.duplicates += 1
                return
            self._held[s] = rest
            if len(self._held) >= self.window:  # the missing frame is given up: the stream finds it lost
                self._release(out_seqs, out_fields)
        elif ahead < m - m // 2:  # further ahead than a reordering: a loss (or a restart)
            self._release(out_seqs, out_fields)
            self._emit(s, rest, out_seqs, out_fields)
        else:  # behind the next one: a duplicate, a frame later than the window, or a counter started again
            self._release(out_seqs, out_fields)
            nxt = self._next
            self._emit(s, rest, out_seqs, out_fields)
            self._next = nxt
            self._after_behind = (s + 1) % m

    def _emit(self, s: int, rest: tuple, out_seqs: list, out_fields: tuple) -> None:
        out_seqs.append(s)
        for f, v in zip(out_fields, rest):
            f.append(v)
        self._next = (s + 1) % self.modulus

    def _release(self, out_seqs: list, out_fields: tuple) -> None:
        """The held frames, in counter order from the next one; the next one is then the last of them plus 1."""
        if not self._held:
            return
        m, nxt = self.modulus, self._next
        for s in sorted(self._held, key=lambda c: (c - nxt) % m):
            self._emit(s, self._held[s], out_seqs, out_fields)
        self._held.clear()
