"""The property-based campaign's kit: profiles, mutations of valid files, and the property.

The property every reader of a user-supplied file is held to (tests/test_fuzz_*.py): it gives
the right result, or an SljaxError of one line naming the file, and nothing else; it allocates
at most a bound derived from the file's real size; it ends within a deadline; and a reader that
writes leaves nothing partial in its output place (checked by the tests that write).

Allocation is measured with tracemalloc, which sees Python's and NumPy's allocations (NumPy
reports its data buffers to it) and the arrays OpenCV's Python bindings return (they are
allocated by NumPy). It does not see OpenCV's internal buffers (a decoder allocates what a
header claims before it reads a pixel), so for images the claim that reaches OpenCV is bounded
instead (`opencv_claims`). A hang is caught by an interval timer that raises in the main thread:
it interrupts Python code, not a call stuck inside a C library, which would stall the test (the
suite's own timeout then names it).

Profiles: `ci` (the default) is small and derandomized, so CI is deterministic; SLJAX_FUZZ=long
selects `long`, many more random examples per reader.
"""

import contextlib
import json
import math
import os
import signal
import struct
import time
import tracemalloc
import zlib
from pathlib import Path
from typing import Any, Callable

import cv2
from hypothesis import HealthCheck, event, settings
from hypothesis import strategies as st

from sljax.errors import SljaxError

LONG = os.environ.get("SLJAX_FUZZ", "").strip().lower() == "long"
# too_slow: each example writes and reads real files (a few ms); data_too_large: byte strings
# mutated by several operations are large by hypothesis's measure, small on disk.
_SUPPRESS = [HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much]
settings.register_profile("ci", derandomize=True, deadline=None, database=None,
                          suppress_health_check=_SUPPRESS, print_blob=False)
settings.register_profile("long", deadline=None, database=None,
                          suppress_health_check=_SUPPRESS)
PROFILE = settings.get_profile("long" if LONG else "ci")
LONG_FACTOR = 20  # the long profile runs this many times the CI examples per reader

DEADLINE_S = 5.0  # per example; a reader of a file of a few KiB takes milliseconds
BASE_BYTES = 4 << 20  # any read's allowance (interpreter, modules' caches, NumPy's temporaries)
PER_BYTE = 64  # what a read may allocate per byte of the file (float32 copies of 8-bit data...)
# An image's: a PNG's data inflates up to 1032 times (deflate's limit), 8 one-bit pixels a byte,
# read as 12 bytes (float32 RGB) a pixel.
IMAGE_PER_BYTE = 1032 * 8 * 12


def fuzz(examples: int) -> settings:
  """Settings for one reader's test: `examples` in CI, LONG_FACTOR times that in the long run."""
  return settings(PROFILE, max_examples=examples * (LONG_FACTOR if LONG else 1))


class Hang(Exception):
  """Raised in the reader by the deadline's timer (an Exception, so that hypothesis shrinks it;
  a reader that swallows it is caught by `check`'s clock)."""


@contextlib.contextmanager
def deadline(seconds: float = DEADLINE_S):
  """Raises Hang in the block when it runs longer than seconds."""
  def ring(signum, frame):  # pylint: disable=unused-argument
    raise Hang(f"no answer within {seconds} s")
  old = signal.signal(signal.SIGALRM, ring)
  signal.setitimer(signal.ITIMER_REAL, seconds)
  try:
    yield
  finally:
    signal.setitimer(signal.ITIMER_REAL, 0)
    signal.signal(signal.SIGALRM, old)


def allowance(*paths: Path, per_byte: int = PER_BYTE) -> int:
  """The allocation bound of a read of these files and folders: BASE_BYTES plus per_byte times
  their real size on disk."""
  total = 0
  for p in paths:
    if p.is_file():
      total += p.stat().st_size
    elif p.is_dir():
      total += sum(q.stat().st_size for q in p.rglob("*") if q.is_file())
  return BASE_BYTES + per_byte * total


def _names(name: str | Path, message: str) -> bool:
  """Whether message names a file: its path, or its folder and its name ("scene DIR: meta.json")."""
  if str(name) in message:
    return True
  return isinstance(name, Path) and str(name.parent) in message and name.name in message


REFUSED = object()  # what `check` returns when the reader refused the file


def check(read: Callable[[], Any], names: str | Path | list, bound: int) -> Any:
  """read()'s result, or REFUSED after an SljaxError of one line naming one of `names` (paths or
  file names); any other exception, an allocation peak above bound or a hang fails."""
  names = [names] if not isinstance(names, list) else names
  tracemalloc.start()
  start = time.monotonic()
  try:
    with deadline():
      try:
        result = read()
      except SljaxError as e:
        message = str(e)
        assert "\n" not in message, f"an error of several lines: {message!r}"
        assert any(_names(n, message) for n in names), \
            f"the error names none of {[str(n) for n in names]}: {message!r}"
        result = REFUSED
    peak = tracemalloc.get_traced_memory()[1]
  finally:
    tracemalloc.stop()
  event("refused" if result is REFUSED else "read")  # the share of each, in the statistics
  assert time.monotonic() - start < DEADLINE_S, f"no answer within {DEADLINE_S} s"
  assert peak <= bound, f"allocated {peak} bytes, the bound is {bound}"
  return result


@contextlib.contextmanager
def opencv_claims(bound: int):
  """Fails when OpenCV is asked to decode an image whose header claims more bytes than bound
  (OpenCV allocates the claim itself, unseen by tracemalloc; 8 bytes a pixel covers 16-bit
  RGBA)."""
  from sljax.io import headers  # pylint: disable=import-outside-toplevel
  real = cv2.imread

  def imread(path, *args):
    try:
      size = headers.image_size(path)
    except (OSError, ValueError):
      size = None
    if size is not None:
      assert size[0] * size[1] * 8 <= bound, (f"OpenCV asked to decode {size[0]}x{size[1]} "
                                              f"pixels from {Path(path).stat().st_size} bytes")
    return real(path, *args)
  cv2.imread = imread
  try:
    yield
  finally:
    cv2.imread = real


# ----------------------------------------------------------------------------- byte mutations

def _position(n: int) -> st.SearchStrategy[int]:
  """A byte offset in [0, n], near the start (headers) as often as anywhere."""
  return st.one_of(st.integers(0, min(n, 40)), st.integers(0, n))


@st.composite
def byte_edit(draw, data: bytes) -> bytes:
  """data with one edit: truncated, a bit flipped, bytes overwritten, inserted or deleted."""
  n = len(data)
  kind = draw(st.sampled_from(["truncate", "flip", "overwrite", "insert", "delete"]))
  at = draw(_position(n))
  if kind == "truncate":
    return data[:at]
  if kind == "flip" and n:
    at = min(at, n - 1)
    return data[:at] + bytes([data[at] ^ (1 << draw(st.integers(0, 7)))]) + data[at + 1:]
  junk = draw(st.binary(min_size=1, max_size=16) | st.sampled_from(
      [b"\xff\xfe", b"\x00", b"\xc3\x28", b"-1", b"99999999999", b"NaN", b"\n", b" "]))
  if kind == "overwrite":
    return data[:at] + junk + data[at + len(junk):]
  if kind == "insert":
    return data[:at] + junk + data[at:]
  return data[:at] + data[at + draw(st.integers(1, 16)):]


@st.composite
def mutated_bytes(draw, data: bytes, max_edits: int = 3) -> bytes:
  """data with one to max_edits byte edits."""
  for _ in range(draw(st.integers(1, max_edits))):
    data = draw(byte_edit(data))
  return data


# Numbers that lie: sizes and counts that are zero, negative, huge or not numbers.
LIES = ["0", "-1", "-7", "1", "3", "65535", "65536", "99999", "2147483647", "4294967296",
        "1e309", "-1e309", "nan", "inf", "1.5", "0x10", "", "abc", "1e30"]


@st.composite
def text_lie(draw, text: bytes) -> bytes:
  """text with one of its numbers replaced by a lie (a size, count or value in a header)."""
  import re  # pylint: disable=import-outside-toplevel
  numbers = list(re.finditer(rb"-?\d+(\.\d+)?([eE][-+]?\d+)?", text))
  if not numbers:
    return text
  m = draw(st.sampled_from(numbers))
  lie = draw(st.sampled_from(LIES) | st.integers(-2**40, 2**40).map(str)).encode()
  return text[:m.start()] + lie + text[m.end():]


# ----------------------------------------------------------------------------- PNG

def png_fix_crcs(data: bytes) -> bytes:
  """data with each whole chunk's CRC recomputed, so that an edit reaches the decoder instead
  of stopping at the CRC check (the edits a tool that writes PNGs wrong would make)."""
  out, pos = bytearray(data), 8
  while pos + 12 <= len(out):
    length = struct.unpack(">I", out[pos:pos + 4])[0]
    end = pos + 12 + length
    if end > len(out):
      break
    out[end - 4:end] = struct.pack(">I", zlib.crc32(bytes(out[pos + 4:end - 4])))
    pos = end
  return bytes(out)


@st.composite
def png_lie(draw, data: bytes) -> bytes:
  """A PNG whose IHDR lies (width, height, bit depth, colour type, interlace), CRC correct."""
  field = draw(st.sampled_from([(16, ">I"), (20, ">I"), (24, ">B"), (25, ">B"), (28, ">B")]))
  at, fmt = field
  top = 2**32 - 1 if fmt == ">I" else 255
  value = draw(st.sampled_from([0, 1, 2, 3, 4, 6, 7, 8, 16, 255, 4096, 65535, 1 << 20,
                                2**31, top]).filter(lambda v: v <= top))
  data = data[:at] + struct.pack(fmt, value) + data[at + struct.calcsize(fmt):]
  return png_fix_crcs(data)


@st.composite
def mutated_png(draw, data: bytes) -> bytes:
  """A valid PNG lied about, edited, or edited with its CRCs made right again."""
  how = draw(st.sampled_from(["lie", "edit", "edit-crc"]))
  if how == "lie":
    return draw(png_lie(data))
  edited = draw(mutated_bytes(data))
  return png_fix_crcs(edited) if how == "edit-crc" else edited


# ----------------------------------------------------------------------------- JSON

STRANGE = [None, True, False, 0, -1, 1.5, 10**30, -10**30, 1e308, math.nan, math.inf,
           -math.inf, "", "x", "\udcff", [], {}, [1, "a"], {"a": None}]


def _paths(value: Any, at: tuple = ()) -> list[tuple]:
  """Every place in a JSON value (keys and indices from the root)."""
  out = [at]
  if isinstance(value, dict):
    for k, v in value.items():
      out += _paths(v, at + (k,))
  elif isinstance(value, list):
    for i, v in enumerate(value):
      out += _paths(v, at + (i,))
  return out


def _replace(value: Any, at: tuple, new: Any, delete: bool = False) -> Any:
  """value with the place `at` set to new (or deleted)."""
  if not at:
    return new
  head, rest = at[0], at[1:]
  copy = dict(value) if isinstance(value, dict) else list(value)
  if delete and not rest:
    del copy[head]
  else:
    copy[head] = _replace(copy[head], rest, new, delete)
  return copy


@st.composite
def json_edit(draw, value: Any) -> Any:
  """value with one place swapped for a value of another type, NaN, inf or a huge number, or
  deleted."""
  at = draw(st.sampled_from(_paths(value)))
  if at and draw(st.booleans()) and draw(st.booleans()):
    return _replace(value, at, None, delete=True)
  new = draw(st.sampled_from(STRANGE) | st.integers(-2**70, 2**70))
  return _replace(value, at, new)


def dumps(value: Any) -> bytes:
  """JSON text as Python writes it, NaN and Infinity included (a hand-edited or foreign file may
  hold them); lone surrogates go out as escapes."""
  return json.dumps(value).encode("utf-8")


@st.composite
def mutated_json(draw, value: Any, text: bytes | None = None) -> bytes:
  """The bytes of a valid JSON value after one to three edits of its values, or of its text
  (truncated, bit flips, non-UTF-8 bytes)."""
  if draw(st.integers(0, 2)):
    for _ in range(draw(st.integers(1, 3))):
      value = draw(json_edit(value))
    return dumps(value)
  return draw(mutated_bytes(dumps(value) if text is None else text))


def write(path: Path, data: bytes) -> None:
  """Writes data to path, replacing whatever is there (a folder included)."""
  import shutil  # pylint: disable=import-outside-toplevel
  if path.is_dir():
    shutil.rmtree(path)
  path.write_bytes(data)


def make_folder(path: Path) -> None:
  """Puts an empty folder where the file path goes (the reverse of a file where a folder goes)."""
  if path.exists():
    path.unlink()
  path.mkdir()


FOLDER = b"<a folder>"  # drawn instead of bytes: a folder where the file goes


def place(path: Path, data: bytes) -> None:
  """Writes data at path (its folders made), or puts a folder there for FOLDER."""
  path.parent.mkdir(parents=True, exist_ok=True)
  if data == FOLDER:
    make_folder(path)
  else:
    write(path, data)


@contextlib.contextmanager
def placed(name: str, data: bytes):
  """A path called name in a fresh temporary folder, holding data (a folder for FOLDER)."""
  import tempfile  # pylint: disable=import-outside-toplevel
  with tempfile.TemporaryDirectory() as d:
    path = Path(d) / name
    place(path, data)
    yield path
