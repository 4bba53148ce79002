"""A sequence of frames read from disk when indexed (a real dataset does not fit in memory)."""
from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import overload

from suit_ros.structures import Frame


class LazySequence(Sequence[Frame]):
    """Subclasses give ``__len__`` and ``frame(k)``; indexing, slicing and iteration read the
    frames on demand."""

    def __len__(self) -> int:
        raise NotImplementedError

    def frame(self, k: int) -> Frame:
        """Read frame ``k`` (0 <= k < len)."""
        raise NotImplementedError

    @overload
    def __getitem__(self, index: int) -> Frame: ...

    @overload
    def __getitem__(self, index: slice) -> list[Frame]: ...

    def __getitem__(self, index: int | slice) -> Frame | list[Frame]:
        if isinstance(index, slice):
            return [self.frame(k) for k in range(*index.indices(len(self)))]
        k = index + len(self) if index < 0 else index
        if not 0 <= k < len(self):
            raise IndexError(f'frame {index} of a {len(self)}-frame sequence')
        return self.frame(k)

    def __iter__(self) -> Iterator[Frame]:
        return (self.frame(k) for k in range(len(self)))
