"""Vectorised bit streams: write and read whole arrays of codes with numpy.

Bits are written most significant bit first, and a stream is packed into bytes most significant
bit first (``numpy.packbits`` order), padded with zero bits to a byte boundary.

Two code families are used (FORMAT.md, "Codes"):

* fixed-width fields of ``w`` bits (``0 <= w <= 64``), unsigned, big-endian bit order;
* Exp-Golomb codes of order ``k`` for an unsigned ``v``: with ``u = v + 2**k`` and
  ``L = u.bit_length()``, the code is ``L - 1 - k`` zero bits, a one bit, then the low ``L - 1``
  bits of ``u``. A *block* of ``N`` Exp-Golomb values writes the ``N`` unary prefixes (zeros and
  the terminating one) first and then the ``N`` mantissas, so that a decoder can split the block
  with two vectorised passes instead of one Python iteration per value. For a single value a
  block is the ordinary interleaved code.

A value coded with Exp-Golomb must be below ``2**MAX_EG_BITS``; readers reject longer codes.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from wire_codec.errors import FormatError, TruncatedError

Bits = NDArray[np.uint8]
U64 = NDArray[np.uint64]
I64 = NDArray[np.int64]

MAX_EG_BITS = 53
"""Exp-Golomb mantissas are at most this many bits (``L - 1 <= MAX_EG_BITS``)."""

_EMPTY_BITS: Bits = np.zeros(0, dtype=np.uint8)


def bit_length(u: I64) -> I64:
    """``int.bit_length`` of each element of a non-negative array of values below ``2**53``."""
    if u.size == 0:
        return np.zeros(0, dtype=np.int64)
    # frexp is exact for integers up to 2**53: u = m * 2**e with 0.5 <= m < 1, so e = bit_length.
    return np.frexp(u.astype(np.float64))[1].astype(np.int64)


def eg_cost(values: I64, k: int) -> int:
    """Total bits of an Exp-Golomb block of order ``k`` for ``values``."""
    if values.size == 0:
        return 0
    ell = bit_length(values + (1 << k))
    return int(np.sum(2 * ell - 1 - k))


def best_eg_order(values: I64, max_order: int = 15) -> int:
    """The Exp-Golomb order in ``0..max_order`` that codes ``values`` in the fewest bits
    (the smallest such order on ties; 0 for an empty array)."""
    return best_eg_orders(values, [int(values.size)], max_order)[0][0]


def best_eg_orders(values: I64, sizes: list[int], max_order: int = 15) -> tuple[list[int], list[int]]:
    """:func:`best_eg_order` for consecutive groups of ``values`` (``sizes`` long) in one pass;
    returns the orders and their costs in bits. Orders above the values' largest bit length
    only add bits, so they are not tried."""
    if values.size == 0:
        return [0] * len(sizes), [0] * len(sizes)
    top = min(max_order, int(np.frexp(float(values.max()))[1]))
    ks = np.arange(top + 1, dtype=np.int64)
    ell = bit_length((values[:, None] + (np.int64(1) << ks)[None, :]).ravel()).reshape(values.size, -1)
    per_value = 2 * ell - 1 - ks[None, :]
    csum = np.concatenate((np.zeros((1, ks.size), dtype=np.int64), np.cumsum(per_value, axis=0)))
    ends = np.cumsum(sizes)
    sums = csum[ends] - csum[ends - np.asarray(sizes)]
    orders, costs = [], []
    for g, size in enumerate(sizes):
        if size == 0:
            orders.append(0)
            costs.append(0)
        else:
            k = int(np.argmin(sums[g]))
            orders.append(k)
            costs.append(int(sums[g, k]))
    return orders, costs


def ceil_log2(n: int) -> int:
    """Bits needed to write any index ``0..n-1`` (0 when ``n <= 1``)."""
    return max(int(n) - 1, 0).bit_length()


class BitWriter:
    """Accumulates bit arrays; :meth:`to_bytes` packs them."""

    def __init__(self) -> None:
        self._parts: list[Bits] = []
        self.n_bits = 0

    def _add(self, bits: Bits) -> None:
        if bits.size:
            self._parts.append(bits)
            self.n_bits += int(bits.size)

    def flags(self, flags: NDArray[np.bool_] | Bits) -> None:
        """One bit per element (truthy -> 1)."""
        self._add(np.asarray(flags).astype(np.uint8).ravel())

    def scalar(self, value: int, width: int) -> None:
        """One unsigned ``width``-bit field."""
        if width == 0:
            return
        if value < 0 or value >> width:
            raise ValueError(f"{value} does not fit in {width} bits")
        self._add(np.array([(value >> s) & 1 for s in range(width - 1, -1, -1)], dtype=np.uint8))

    def fixed(self, values: U64 | I64, width: int) -> None:
        """Each value as an unsigned ``width``-bit field (``0 <= width <= 64``)."""
        v = np.asarray(values).astype(np.uint64).ravel()
        if width == 0 or v.size == 0:
            return
        shifts = np.arange(width - 1, -1, -1, dtype=np.uint64)
        self._add(((v[:, None] >> shifts[None, :]) & np.uint64(1)).astype(np.uint8).ravel())

    def wide(self, values: list[int], width: int) -> None:
        """Each value (a non-negative Python int below ``2**width``) as an unsigned
        ``width``-bit field, for any ``width`` (the same bits as :meth:`fixed` where both
        apply)."""
        if width == 0 or not values:
            return
        nb = (width + 7) // 8
        raw = b"".join(int(v).to_bytes(nb, "big") for v in values)
        bits = np.unpackbits(np.frombuffer(raw, dtype=np.uint8)).reshape(len(values), 8 * nb)
        self._add(np.ascontiguousarray(bits[:, 8 * nb - width :]).ravel())

    def varwidth(self, values: I64, widths: I64) -> None:
        """Value ``i`` as an unsigned field of ``widths[i]`` bits (``widths[i] <= 64``)."""
        v = np.asarray(values).astype(np.uint64).ravel()
        w = np.asarray(widths, dtype=np.int64).ravel()
        if v.size == 0:
            return
        top = int(w.max())
        if top == 0:
            return
        shift = w[:, None] - 1 - np.arange(top, dtype=np.int64)[None, :]
        mask = shift >= 0
        bits = (v[:, None] >> np.where(mask, shift, 0).astype(np.uint64)) & np.uint64(1)
        self._add(bits[mask].astype(np.uint8))

    def unary(self, zeros: I64) -> None:
        """Value ``i`` as ``zeros[i]`` zero bits followed by a one bit."""
        z = np.asarray(zeros, dtype=np.int64).ravel()
        if z.size == 0:
            return
        ends = np.cumsum(z + 1) - 1
        out = np.zeros(int(ends[-1]) + 1, dtype=np.uint8)
        out[ends] = 1
        self._add(out)

    def eg_block(self, values: I64, k: int | I64) -> None:
        """An Exp-Golomb block: all unary prefixes, then all mantissas. ``k`` is one order for
        every value or an array of per-value orders."""
        v = np.asarray(values, dtype=np.int64).ravel()
        if v.size == 0:
            return
        u = v + (np.int64(1) << np.asarray(k, dtype=np.int64))
        ell = bit_length(u)
        self.unary(ell - 1 - k)
        self.varwidth(u - (np.int64(1) << (ell - 1)), ell - 1)

    def eg(self, value: int, k: int = 0) -> None:
        """One Exp-Golomb value of order ``k``."""
        u = int(value) + (1 << k)
        ell = u.bit_length()
        self.scalar(1, ell - k)  # ell-1-k zeros then a one
        self.scalar(u - (1 << (ell - 1)), ell - 1)

    def to_bits(self) -> Bits:
        return np.concatenate(self._parts) if self._parts else _EMPTY_BITS

    def to_bytes(self) -> bytes:
        """The stream packed MSB first, zero-padded to whole bytes."""
        return np.packbits(self.to_bits()).tobytes()


class BitReader:
    """Reads what :class:`BitWriter` writes, checking every length against what is left.

    Raises :class:`~wire_codec.errors.TruncatedError` when the stream ends too early and
    :class:`~wire_codec.errors.FormatError` for an over-long Exp-Golomb code.
    """

    def __init__(self, data: bytes, what: str = "body") -> None:
        self.bits: Bits = np.unpackbits(np.frombuffer(data, dtype=np.uint8))
        self.pos = 0
        self.what = what

    @property
    def remaining(self) -> int:
        return int(self.bits.size) - self.pos

    def need(self, n_bits: int, what: str) -> None:
        if n_bits > self.remaining:
            raise TruncatedError(
                f"{self.what} ends inside {what}: needs {n_bits} more bits, {self.remaining} left"
            )

    def flags(self, count: int, what: str) -> Bits:
        self.need(count, what)
        out = self.bits[self.pos : self.pos + count]
        self.pos += count
        return out

    def scalar(self, width: int, what: str) -> int:
        self.need(width, what)
        v = 0
        for b in self.bits[self.pos : self.pos + width].tolist():
            v = (v << 1) | b
        self.pos += width
        return v

    def fixed(self, count: int, width: int, what: str) -> U64:
        if width == 0 or count == 0:
            return np.zeros(count, dtype=np.uint64)
        self.need(count * width, what)
        seg = self.bits[self.pos : self.pos + count * width].reshape(count, width).astype(np.uint64)
        self.pos += count * width
        shifts = np.arange(width - 1, -1, -1, dtype=np.uint64)
        return np.asarray((seg << shifts[None, :]).sum(axis=1, dtype=np.uint64), dtype=np.uint64)

    def wide(self, count: int, width: int, what: str) -> list[int]:
        """``count`` unsigned ``width``-bit fields of any width, as Python ints (checks that
        the bits are there before allocating anything)."""
        if width == 0 or count == 0:
            return [0] * count
        self.need(count * width, what)
        seg = self.bits[self.pos : self.pos + count * width].reshape(count, width)
        self.pos += count * width
        nb = (width + 7) // 8
        padded = np.zeros((count, 8 * nb), dtype=np.uint8)
        padded[:, 8 * nb - width :] = seg
        raw = np.packbits(padded, axis=1).tobytes()
        return [int.from_bytes(raw[i * nb : (i + 1) * nb], "big") for i in range(count)]

    def varwidth(self, widths: I64, what: str) -> I64:
        """Unsigned fields of the given widths (each at most 63 bits), as int64."""
        if widths.size == 0:
            return np.zeros(0, dtype=np.int64)
        total = int(widths.sum())
        self.need(total, what)
        top = int(widths.max())
        if top == 0:
            return np.zeros(widths.size, dtype=np.int64)
        starts = self.pos + np.cumsum(widths) - widths
        j = np.arange(top, dtype=np.int64)
        shift = widths[:, None] - 1 - j[None, :]
        mask = shift >= 0
        idx = np.where(mask, starts[:, None] + j[None, :], 0)
        bits = self.bits[idx].astype(np.int64) & mask
        self.pos += total
        return np.asarray((bits << np.where(mask, shift, 0)).sum(axis=1), dtype=np.int64)

    def unary(self, count: int, max_zeros: int, what: str) -> I64:
        """``count`` unary codes (zeros then a one); rejects a code with more than
        ``max_zeros`` zeros as soon as it is seen."""
        if count == 0:
            return np.zeros(0, dtype=np.int64)
        window = self.bits[self.pos : self.pos + count * (max_zeros + 1)]
        ones = window.nonzero()[0][:count]
        zeros = np.empty(ones.size, dtype=np.int64)
        if ones.size:
            zeros[0] = ones[0]
            zeros[1:] = ones[1:] - ones[:-1] - 1
        if ones.size < count or int(zeros.max()) > max_zeros:
            tail = window.size - (int(ones[-1]) + 1 if ones.size else 0)
            if (zeros.size and int(zeros.max()) > max_zeros) or tail > max_zeros:
                raise FormatError(f"{self.what}: a code in {what} is longer than {max_zeros + 1} bits")
            raise TruncatedError(f"{self.what} ends inside {what}")
        self.pos += int(ones[-1]) + 1
        return np.asarray(zeros, dtype=np.int64)

    def eg_block(self, count: int, k: int | I64, what: str) -> I64:
        """``count`` Exp-Golomb values written by :meth:`BitWriter.eg_block` (``k`` one order or
        an array of ``count`` orders); rejects a mantissa longer than ``MAX_EG_BITS``."""
        if count == 0:
            return np.zeros(0, dtype=np.int64)
        ks = np.asarray(k, dtype=np.int64)
        zeros = self.unary(count, MAX_EG_BITS - int(ks.min()), what)
        widths = zeros + ks
        if ks.ndim and int(widths.max()) > MAX_EG_BITS:
            raise FormatError(f"{self.what}: a code in {what} is longer than {MAX_EG_BITS} bits")
        mant = self.varwidth(widths, what)
        return np.asarray(mant + (np.int64(1) << widths) - (np.int64(1) << ks), dtype=np.int64)

    def eg(self, k: int, what: str) -> int:
        """One Exp-Golomb value of order ``k`` (a scalar path: no array work)."""
        max_zeros = MAX_EG_BITS - k
        window = self.bits[self.pos : self.pos + max_zeros + 1]
        zeros = int(window.argmax()) if window.size else 0
        if window.size == 0 or not window[zeros]:
            if window.size == max_zeros + 1:
                raise FormatError(f"{self.what}: the code of {what} is longer than {max_zeros + 1} bits")
            raise TruncatedError(f"{self.what} ends inside {what}")
        self.pos += zeros + 1
        return (1 << (zeros + k)) + self.scalar(zeros + k, what) - (1 << k)
