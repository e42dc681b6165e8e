"""One progress reporter, built where a user asks for progress and passed down the layers.

Every long call of mjstamp takes `progress`, one of what a user may pass:

- None: status lines, and a tqdm bar on a terminal; a loop that draws a bar
  (the STAMP loop, the sweeps) writes lines in its place only in a log or a
  pipe, where a bar shows nothing (the default of `solve`, `modes.sweep`);
- True: the bar and the lines; False: nothing (the default of the calls a
  command runs for its user, such as `check_scene`);
- a callable that takes each status line (a notebook's own logger);
- a `Progress`, handed on as it is.

`Progress.of` turns any of them into one object; each layer speaks under its
own prefix (`progress.under("stamp")("compiling")` prints "[stamp] compiling")
and asks it whether to draw a bar (`bar`) or to write lines in its place
(`lines`). Imports only the standard library, so the engine (`svgd/`) may use it.
"""

from __future__ import annotations

import dataclasses
import sys
from collections.abc import Callable

__all__ = ["QUIET", "Progress", "ProgressLike"]


@dataclasses.dataclass(frozen=True)
class Progress:
    """Status lines on stderr under a prefix, to a callable, or nothing; and whether bars show.

    Attributes:
      mode: None (a bar on a terminal, lines elsewhere), True (both) or False (nothing).
      prefix: the word in brackets before each line ("solve" prints "[solve] ...").
      sink: where lines go instead of stderr (they are then given without the prefix).
    """

    mode: bool | None = None
    prefix: str = "mjstamp"
    sink: Callable[[str], None] | None = None

    @classmethod
    def of(cls, progress: Progress | bool | Callable[[str], None] | None,
           prefix: str = "mjstamp") -> Progress:
        """The reporter for what a caller passed as `progress` (see the module docstring)."""
        if isinstance(progress, Progress):
            return progress
        if progress is None or isinstance(progress, bool):
            return cls(progress, prefix)
        if callable(progress):
            return cls(True, prefix, sink=progress)
        raise TypeError(f"progress={progress!r}: valid: None, True, False, a callable taking "
                        "each status line, or a mjstamp.progress.Progress")

    def under(self, prefix: str) -> Progress:
        """The same reporter speaking under another prefix (a lower layer's own)."""
        return dataclasses.replace(self, prefix=prefix)

    def __call__(self, message: str) -> None:
        """Reports one status line (nothing when `mode` is False)."""
        if self.mode is False:
            return
        if self.sink is not None:
            self.sink(message)
        else:
            print(f"[{self.prefix}] {message}", file=sys.stderr, flush=True)

    @property
    def bar(self) -> bool:
        """Whether to draw a tqdm bar: asked for, or None on a terminal; never to a callable."""
        if self.sink is not None:
            return False
        return sys.stderr.isatty() if self.mode is None else bool(self.mode)

    @property
    def lines(self) -> bool:
        """Whether status lines stand in for a bar: None away from a terminal, or a callable.

        N.B. without a terminal tqdm writes nothing a log can show.
        """
        return self.sink is not None or (self.mode is None and not sys.stderr.isatty())


#: What a `progress` argument takes (see the module docstring).
ProgressLike = Progress | bool | Callable[[str], None] | None

#: The reporter that says nothing.
QUIET = Progress(False)
