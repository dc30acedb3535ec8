"""Values of many entries laid out entry by entry, for loops whose SIMD lanes read one entry.

In a symbolic loop where the lanes of a SIMD packet all read entry j (the tiled
rasterizer's sorted splats, stage 2's other set of samples), one gather per value loads
the same address 16 times per value. Laid out entry by entry, an entry's values are
contiguous, and Dr.Jit reads them with one *packet gather* (contiguous loads and a
transpose) per packet of up to PACKET_MAX floats, and adds into them with one *packet
scatter-add* (LLVM, ``ReduceMode.Expand``; other modes and CUDA fall back to one
scatter-add per value).
"""

from __future__ import annotations

import dataclasses

import drjit as dr
import mitsuba as mi

# Most floats that one packet gather or scatter-add moves per lane: an AVX-512 register.
PACKET_MAX = 16


def packet_widths(n: int) -> list:
    """Floats per entry of each packet that holds ``n`` values per entry: powers of two up
    to PACKET_MAX, the last zero padded (22 -> 16, 8)."""
    out = []
    while n > 0:
        out.append(min(PACKET_MAX, 1 << (n - 1).bit_length()))
        n -= out[-1]
    return out


def _padded(values: list, widths: list, lanes: int):
    """``values`` cut into one mi.ArrayXf per packet of ``widths``, the last zero padded."""
    o = 0
    for width in widths:
        part = list(values[o:o + width])
        yield mi.ArrayXf(part + [dr.zeros(mi.Float, lanes)] * (width - len(part)))
        o += width


@dataclasses.dataclass
class Packed:
    """``count`` float values of each of ``size`` entries: one flat array per packet of
    ``packet_widths(count)``, value k of entry i at ``i * width + k`` of its packet."""

    packs: list  # [size * width] per packet
    size: int
    count: int

    @staticmethod
    def of(values: list) -> Packed:
        """``values`` ([size] floats each; UInt32 through ``dr.reinterpret_array``) packed
        and evaluated."""
        size = dr.width(values[0])
        packs = []
        for part in _padded(values, packet_widths(len(values)), size):
            packed = dr.zeros(mi.Float, size * len(part))
            dr.scatter(packed, part, dr.arange(mi.UInt32, size))
            packs.append(packed)
        dr.eval(packs)
        return Packed(packs, size, len(values))

    @staticmethod
    def zeros(size: int, count: int) -> Packed:
        """``count`` zero values per entry (sums that ``scatter_add`` adds into)."""
        return Packed([dr.zeros(mi.Float, size * w) for w in packet_widths(count)], size,
                      count)

    def _width(self, packed: mi.Float) -> int:
        return dr.width(packed) // self.size

    def permuted(self, index: mi.UInt32) -> Packed:
        """Entries ``index`` (a permutation, or any [M] selection), packed in that order: one
        packet gather per entry, where gathering each value alone from arrays laid out
        value by value reads one cache line per value."""
        return Packed.of(self.read(index, dr.width(index)))

    def read(self, index: mi.UInt32, n: int) -> list:
        """The ``count`` values of entry ``index`` for each of ``n`` lanes."""
        v = []
        for packed in self.packs:
            v += list(dr.gather(mi.ArrayXf, packed, index, shape=(self._width(packed), n)))
        return v[:self.count]

    def scatter_add(self, values: list, index: mi.UInt32, active: mi.Bool,
                    mode: dr.ReduceMode) -> None:
        """Add ``values`` (``count`` arrays [lanes]) into entry ``index`` of each lane."""
        widths = [self._width(packed) for packed in self.packs]
        for packed, part in zip(self.packs, _padded(values, widths, dr.width(index)),
                                strict=True):
            dr.scatter_reduce(dr.ReduceOp.Add, packed, part, index, active=active, mode=mode)

    def column(self, k: int, entries: mi.UInt32 | None = None) -> mi.Float:
        """Value k of every entry [size], or of ``entries`` in their order."""
        if entries is None:
            entries = dr.arange(mi.UInt32, self.size)
        for packed in self.packs:
            width = self._width(packed)
            if k < width:
                return dr.gather(mi.Float, packed, entries * width + k)
            k -= width
        raise IndexError(k)
