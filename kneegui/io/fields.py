"""Number fields of fixed-column and free-format (comma) keyword cards.

Fast paths work on (n, width) uint8 arrays cut out of the deck bytes; when a fast path meets
something it does not understand it reports the row, and the caller re-parses that card with the
slow, exact per-field functions (:func:`parse_float_field`, :func:`parse_int_field`), which either
accept the text or raise with a precise message.
"""

from __future__ import annotations

import math
import re

import numpy as np
from numpy.typing import NDArray

_SPACE, _MINUS, _PLUS, _ZERO = 32, 45, 43, 48
_MAX_SIGNIFICANT = 17

# Fortran-style floats LS-DYNA accepts: 1.5e3, 1.5E+3, 1.5D3, 1.5d-3, 1.5+3, 1.5-3, .5, 5.
_FLOAT_RE = re.compile(r"^[+-]?(?:\d+\.?\d*|\.\d+)(?:(?:[eEdD][+-]?\d+)|(?:[+-]\d+))?$")
_INT_RE = re.compile(r"^[+-]?\d+$")


class FieldError(ValueError):
    """A field's text is not a number of the expected kind."""


def parse_float_field(text: str | bytes) -> float:
    """Parse one real field the way LS-DYNA does.

    Blank means 0. Accepts ``E``/``D`` exponents and the Fortran short form ``1.5+3``.

    Raises
    ------
    FieldError
        If the text is not a finite real number.
    """
    s = text.decode("latin-1") if isinstance(text, bytes) else text
    s = s.strip()
    if not s:
        return 0.0
    if not _FLOAT_RE.match(s):
        raise FieldError(f"{s!r} is not a real number")
    t = s.replace("d", "e").replace("D", "e")
    if "e" not in t and "E" not in t:
        # 1.5+3 / 1.5-3: an exponent sign after the mantissa's first character
        m = re.match(r"^([+-]?[\d.]+)([+-]\d+)$", t)
        if m:
            t = f"{m.group(1)}e{m.group(2)}"
    value = float(t)
    if not math.isfinite(value):
        raise FieldError(f"{s!r} is not a finite number")
    return value


def parse_int_field(text: str | bytes) -> int:
    """Parse one integer field; blank means 0.

    Raises
    ------
    FieldError
        If the text is not an integer.
    """
    s = text.decode("latin-1") if isinstance(text, bytes) else text
    s = s.strip()
    if not s:
        return 0
    if not _INT_RE.match(s):
        raise FieldError(f"{s!r} is not an integer")
    return int(s)


def parse_int_columns(chars: NDArray[np.uint8]) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """Parse right- or left-aligned integer fields, one per row, vectorised.

    Parameters
    ----------
    chars : (n, w) ndarray of uint8
        The field's bytes (spaces where the line was shorter).

    Returns
    -------
    values : (n,) ndarray of int64
        Parsed values (blank fields are 0).
    bad : (n,) ndarray of bool
        Rows whose text is not a plain integer (re-parse them with :func:`parse_int_field`).
    """
    n, w = chars.shape
    if w > 18:  # int64 holds 18 digits safely; longer fields take the exact path
        values = np.zeros(n, dtype=np.int64)
        bad = np.zeros(n, dtype=bool)
        for i in range(n):
            try:
                values[i] = parse_int_field(chars[i].tobytes())
            except FieldError:
                bad[i] = True
        return values, bad
    if w == 8:
        values, simple = _parse_int8_swar(chars)
        bad = np.zeros(n, dtype=bool)
        rest = np.flatnonzero(~simple)
        if len(rest):
            values[rest], bad[rest] = _parse_int_general(chars[rest])
        return values, bad
    # fast path: right-aligned unsigned integers (what writers produce)
    d = chars - np.uint8(_ZERO)
    digit = d < 10
    space = chars == _SPACE
    one_run = ~np.any(digit[:, :-1] & ~digit[:, 1:], axis=1)  # no digit followed by a non-digit
    simple = digit[:, -1] & np.all(digit | space, axis=1) & one_run
    values = np.zeros(n, dtype=np.int64)
    if simple.any():
        pow10 = 10 ** np.arange(w - 1, -1, -1, dtype=np.int64)
        dm = np.where(digit[simple], d[simple], 0).astype(np.int64)
        values[simple] = dm @ pow10
    bad = np.zeros(n, dtype=bool)
    rest = np.flatnonzero(~simple)
    if len(rest):
        values[rest], bad[rest] = _parse_int_general(chars[rest])
    return values, bad


_ONES = np.uint64(0x0101010101010101)
_LOW7 = np.uint64(0x0001010101010101)


def _parse_int8_swar(chars: NDArray[np.uint8]) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """Right-aligned unsigned 8-character integer fields, eight characters at a time.

    Each field is one little-endian uint64 (SIMD within a register): validity checks are whole-
    word bit tests and the digits are combined in three multiply-shift-mask steps.

    Returns
    -------
    values : (n,) ndarray of int64
    simple : (n,) ndarray of bool
        Rows this path read; the others (blank, signed, left-aligned, invalid) need the general
        parser.
    """
    c = np.ascontiguousarray(chars)
    d = c - np.uint8(_ZERO)
    digit = (d < 10).view("<u8").reshape(-1)
    space = (c == _SPACE).view("<u8").reshape(-1)
    simple = ((digit | space) == _ONES) & ((digit >> np.uint64(56)) == 1)
    # one run of digits: no digit byte followed by a non-digit byte
    simple &= (digit & ~(digit >> np.uint64(8)) & _LOW7) == 0
    v = d.view("<u8").reshape(-1).copy()
    v &= digit * np.uint64(0xFF)  # spaces -> 0
    t = np.empty_like(v)
    for mul, shift, mask in (
        (10, 8, 0x00FF00FF00FF00FF),
        (100, 16, 0x0000FFFF0000FFFF),
        (10000, 32, 0xFFFFFFFF),
    ):
        np.right_shift(v, np.uint64(shift), out=t)
        v *= np.uint64(mul)
        v += t
        v &= np.uint64(mask)
    values = v.view(np.int64)
    values[~simple] = 0
    return values, simple


def _parse_int_general(chars: NDArray[np.uint8]) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """Blank, left-aligned and signed integer fields; flags anything else as bad."""
    n, w = chars.shape
    c = chars.astype(np.int16)
    digit = (c >= _ZERO) & (c <= _ZERO + 9)
    space = c == _SPACE
    sign = (c == _MINUS) | (c == _PLUS)
    nonspace = ~space
    bad = np.any(~(digit | space | sign), axis=1)
    # the non-space characters must form one run: optional sign then digits
    any_ns = nonspace.any(axis=1)
    first = np.argmax(nonspace, axis=1)
    last = w - 1 - np.argmax(nonspace[:, ::-1], axis=1)
    run = np.count_nonzero(nonspace, axis=1)
    bad |= any_ns & (run != last - first + 1)
    n_sign = np.count_nonzero(sign, axis=1)
    bad |= n_sign > 1
    rows = np.arange(n)
    bad |= (n_sign == 1) & ~sign[rows, first]
    bad |= (n_sign == 1) & (run == 1)
    value = np.zeros(n, dtype=np.int64)
    d = c - _ZERO
    for j in range(w):
        value = np.where(digit[:, j], value * 10 + d[:, j], value)
    negative = np.any(c == _MINUS, axis=1)
    value = np.where(negative, -value, value)
    return value, bad


def parse_float_columns(chars: NDArray[np.uint8]) -> NDArray[np.float64] | None:
    """Parse real fields, one per row, vectorised.

    Parameters
    ----------
    chars : (n, w) ndarray of uint8
        The field's bytes.

    Returns
    -------
    (n,) ndarray of float64, or None
        ``None`` when some field is not a plain decimal/E-format number (Fortran ``D`` exponents,
        ``1.5+3``, garbage) or is not finite: re-parse those cards with :func:`parse_float_field`.
    """
    n, w = chars.shape
    if n == 0:
        return np.zeros(0)
    buf = np.full((n, w + 1), _SPACE, dtype=np.uint8)
    buf[:, :w] = chars
    blank = np.all(chars == _SPACE, axis=1)
    if blank.any():
        buf[blank, w - 1] = _ZERO
    try:
        values = np.fromstring(buf.tobytes(), dtype=np.float64, sep=" ")
    except ValueError:
        return None
    if len(values) != n or not np.all(np.isfinite(values)):
        return None
    return values


def format_fixed_width(values: NDArray[np.float64], width: int) -> NDArray[np.uint8]:
    """Format reals into fields of exactly ``width`` characters with as many digits as fit.

    One leading blank is always kept, so that a field never touches the one before it, and at
    most 17 significant digits are written (all a float64 holds).

    Fixed-point notation is used when it gives more significant digits, E-notation otherwise.

    Parameters
    ----------
    values : (n,) ndarray of float
        Finite values.
    width : int
        Field width (16 for standard LS-DYNA coordinates, 20 for long format).

    Returns
    -------
    (n, width) ndarray of uint8
        The right-aligned text of each field.

    Raises
    ------
    FieldError
        If a value is not finite or cannot be written in ``width`` characters.
    """
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    n = len(v)
    out = np.full((n, width), _SPACE, dtype=np.uint8)
    if n == 0:
        return out
    if not np.all(np.isfinite(v)):
        raise FieldError("cannot write a non-finite coordinate")
    neg = (v < 0) | ((v == 0) & np.signbit(v))
    a = np.abs(v)
    room = width - 1  # one leading blank keeps whitespace-splitting tools working
    with np.errstate(divide="ignore"):
        int_digits = np.where(a >= 1, np.floor(np.log10(np.maximum(a, 1))).astype(np.int64) + 1, 1)
    lead = _leading_zeros(a)
    # fixed: sign + int digits + "." + decimals; never more than 17 significant digits
    dec_fixed = room - neg - int_digits - 1
    cap = np.where(a >= 1, _MAX_SIGNIFICANT - int_digits, _MAX_SIGNIFICANT + lead)
    dec_fixed = np.minimum(dec_fixed, np.maximum(cap, 1))
    sig_fixed = np.where(a >= 1, int_digits + dec_fixed, dec_fixed - lead)
    # exponent: sign + d + "." + decimals + e±XX (or e±XXX)
    exp_len = np.where((a != 0) & ((a >= 1e100) | (a < 1e-99)), 5, 4)
    dec_exp = np.minimum(room - neg - 2 - exp_len, _MAX_SIGNIFICANT - 1)
    use_fixed = (a == 0) | ((dec_fixed >= 1) & (sig_fixed >= dec_exp + 1))
    dec = np.where(use_fixed, np.maximum(dec_fixed, 0), dec_exp)
    if np.any(~use_fixed & (dec_exp < 1)):
        bad = float(v[~use_fixed & (dec_exp < 1)][0])
        raise FieldError(f"value {bad!r} does not fit a {width}-character field")
    for fixed in (True, False):
        kind = "f" if fixed else "e"
        for p in np.unique(dec[use_fixed == fixed]).tolist():
            sel = np.flatnonzero((use_fixed == fixed) & (dec == p))
            group = v[sel].tolist()
            joined = (f"%{width}.{p}{kind}" * len(group)) % tuple(group)
            if len(joined) == len(group) * width and _all_lead_blank(joined, width):
                out[sel] = np.frombuffer(joined.encode("ascii"), dtype=np.uint8).reshape(-1, width)
                continue
            # rounding added a digit somewhere (9.99.. -> 10.0): one decimal fewer for those
            for i, x in zip(sel.tolist(), group, strict=True):
                q = p
                text = f"%{width}.{q}{kind}" % x
                while len(text) > width or text[0] != " ":
                    q -= max(len(text) - width, 1)
                    if q < 0:
                        raise FieldError(f"value {x!r} does not fit a {width}-character field")
                    text = f"%{width}.{q}{kind}" % x
                out[i] = np.frombuffer(text.encode("ascii"), dtype=np.uint8)
    return out


def _all_lead_blank(joined: str, width: int) -> bool:
    return joined[::width].count(" ") == len(joined) // width


def _leading_zeros(a: NDArray[np.float64]) -> NDArray[np.int64]:
    """For 0 < a < 1, the number of zeros after the decimal point before the first digit."""
    with np.errstate(divide="ignore"):
        lz = np.where((a > 0) & (a < 1), -np.floor(np.log10(np.where(a > 0, a, 1))) - 1, 0)
    return lz.astype(np.int64)


def format_free_float(value: float) -> str:
    """Shortest text that reads back to exactly ``value`` (for comma-separated cards)."""
    return repr(float(value))
