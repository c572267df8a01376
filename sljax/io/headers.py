"""Image sizes read from file headers, before anything is decoded; PNGs checked whole.

A header can claim any size: OpenCV allocates what a PNG's IHDR says before it reads a pixel,
and fails with an assertion (cv2.error, a traceback) above its own limit. Every image sljax
reads is therefore sized from its header first (PNG, JPEG, BMP, PNM, TIFF), checked against
MAX_PIXELS and, in a dataset, against the scene's size, and only then decoded.

png_check is the pre-flight's whole-file check of a PNG: the chunks and their CRC-32s, then
the image data inflated to the end (a zlib stream written wrong behind correct CRCs), without
unfiltering or converting pixels.
"""

import os
import struct
import zlib
from typing import BinaryIO

from sljax.errors import SljaxError

# 2^28 = 268 megapixels: one such view is 3 GiB as float32 RGB, and OpenCV's own limit (2^30,
# CV_IO_MAX_IMAGE_PIXELS) fails with an assertion instead of an answer.
MAX_PIXELS = 1 << 28

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# PNG colour type -> (samples per pixel, allowed bit depths)
_PNG_COLOURS = {0: (1, (1, 2, 4, 8, 16)), 2: (3, (8, 16)), 3: (1, (1, 2, 4, 8)),
                4: (2, (8, 16)), 6: (4, (8, 16))}
# Adam7: (first row, first column, row step, column step) of each pass
_ADAM7 = ((0, 0, 8, 8), (0, 4, 8, 8), (4, 0, 8, 4), (0, 2, 4, 4), (2, 0, 4, 2), (0, 1, 2, 2),
          (1, 0, 2, 1))
_INFLATE_STEP = 1 << 20  # bytes inflated at a time: memory stays small whatever the size
# Deflate's largest ratio: one 258-byte match in about two bits (RFC 1951), so a PNG's image
# data needs at least 1/1032 of its inflated size in the file.
DEFLATE_MAX_RATIO = 1032


def pixel_problem(width: int, height: int) -> str | None:
  """Why an image of width x height pixels is refused (empty, or above MAX_PIXELS); None if not."""
  if width <= 0 or height <= 0:
    return f"corrupt: size {width}x{height}"
  if width * height > MAX_PIXELS:
    return (f"its header claims {width}x{height} pixels ({width * height / 1e6:.0f} "
            f"megapixels), more than sljax reads ({MAX_PIXELS / 1e6:.0f} megapixels)")
  return None


# ----------------------------------------------------------------------------- sizes


def _png_size(f: BinaryIO) -> tuple[int, int]:
  head = f.read(24)
  if len(head) < 24 or head[12:16] != b"IHDR":
    raise ValueError("corrupt: the first chunk is not IHDR")
  return struct.unpack(">II", head[16:24])


def _jpeg_size(f: BinaryIO) -> tuple[int, int]:
  f.seek(2)
  while True:
    byte = f.read(1)
    while byte == b"\xff":  # fill bytes before a marker
      byte = f.read(1)
    if not byte:
      raise ValueError("truncated JPEG (no frame header)")
    marker = byte[0]
    if marker in (0x01, *range(0xD0, 0xD8)):  # markers without a length
      continue
    length = f.read(2)
    if len(length) < 2:
      raise ValueError("truncated JPEG (no frame header)")
    size = struct.unpack(">H", length)[0]
    # SOF0..SOF15 carry the frame size, except DHT (C4), JPG (C8) and DAC (CC).
    if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
      frame = f.read(5)
      if len(frame) < 5:
        raise ValueError("truncated JPEG frame header")
      height, width = struct.unpack(">HH", frame[1:5])
      return width, height
    if marker == 0xD9 or size < 2:
      raise ValueError("corrupt JPEG (no frame header)")
    f.seek(size - 2, os.SEEK_CUR)


def _bmp_size(f: BinaryIO) -> tuple[int, int]:
  head = f.read(26)
  if len(head) < 26:
    raise ValueError("truncated BMP header")
  if struct.unpack("<I", head[14:18])[0] == 12:  # OS/2 BITMAPCOREHEADER: 16-bit sizes
    return struct.unpack("<HH", head[18:22])
  width, height = struct.unpack("<ii", head[18:26])
  return width, abs(height)  # a negative height is a top-down bitmap


def _pnm_size(f: BinaryIO) -> tuple[int, int]:
  head = f.read(1024)
  fields: list[bytes] = []
  for line in head[2:].split(b"\n"):
    fields += line.split(b"#", 1)[0].split()
    if len(fields) >= 2:
      break
  try:
    return int(fields[0]), int(fields[1])
  except (IndexError, ValueError):
    raise ValueError("corrupt PNM header (no width and height)") from None


def _tiff_size(f: BinaryIO) -> tuple[int, int]:
  head = f.read(8)
  order = "<" if head[:2] == b"II" else ">"
  f.seek(struct.unpack(order + "I", head[4:8])[0])
  count_bytes = f.read(2)
  if len(count_bytes) < 2:
    raise ValueError("truncated TIFF (no image directory)")
  entries = f.read(12 * struct.unpack(order + "H", count_bytes)[0])
  size: dict[int, int] = {}
  for k in range(0, len(entries) - 11, 12):
    tag, kind = struct.unpack(order + "HH", entries[k:k + 4])
    if tag in (256, 257) and kind in (3, 4):  # ImageWidth, ImageLength as SHORT or LONG
      size[tag] = struct.unpack(order + ("H" if kind == 3 else "I"), entries[k + 8:k + 8 + (
          2 if kind == 3 else 4)])[0]
  if len(size) < 2:
    raise ValueError("corrupt TIFF (no image width and length)")
  return size[256], size[257]


def _reader(head: bytes):
  """The size reader for a file starting with head, or None for a format not listed here."""
  if head[:8] == PNG_SIGNATURE:
    return _png_size
  if head[:3] == b"\xff\xd8\xff":
    return _jpeg_size
  if head[:2] == b"BM":
    return _bmp_size
  if head[:1] == b"P" and head[1:2] in b"123456" and head[2:3].isspace():
    return _pnm_size
  if head[:4] in (b"II*\x00", b"MM\x00*"):
    return _tiff_size
  return None


def image_size(path: str | os.PathLike) -> tuple[int, int] | None:
  """(width, height) from an image file's header, without decoding; None for a format whose
  header is not read here (OpenCV then decodes it, guarded); ValueError for a broken header."""
  with open(path, "rb") as f:
    return _size_of(f)


def _size_of(f: BinaryIO) -> tuple[int, int] | None:
  """image_size of an open file (read from its start)."""
  f.seek(0)
  reader = _reader(f.read(8))
  if reader is None:
    return None
  f.seek(0)
  try:
    return reader(f)
  except struct.error:
    raise ValueError("truncated image header") from None


def check_image_size(path: str | os.PathLike, want_hw: tuple[int, int] | None = None,
                     against: str = "im0.png") -> tuple[int, int] | None:
  """The (height, width) an image's header claims, or None where unread; SljaxError naming the
  file when it is above MAX_PIXELS or, given want_hw, not the size of `against`."""
  path = os.fspath(path)
  try:
    with open(path, "rb") as f:  # once: the loader reads every view of every batch this way
      return _checked_size(f, path, want_hw, against)
  except FileNotFoundError:
    raise SljaxError(f"{path}: missing") from None
  except OSError as e:
    raise SljaxError(f"{path}: cannot read ({e.strerror or e})") from None


def _checked_size(f: BinaryIO, path: str, want_hw: tuple[int, int] | None,
                  against: str) -> tuple[int, int] | None:
  """check_image_size of the open file f."""
  try:
    size = _size_of(f)
  except ValueError as e:
    raise SljaxError(f"{path}: not a readable image ({e})") from None
  if size is None:
    return None
  width, height = size
  problem = pixel_problem(width, height)
  if problem is not None:
    raise SljaxError(f"{path}: {problem}")
  if want_hw is not None and (height, width) != tuple(want_hw):
    raise SljaxError(f"{path}: size {width}x{height} differs from {against} "
                     f"({want_hw[1]}x{want_hw[0]})")
  problem = _png_room_problem(f, width, height)
  if problem is not None:  # OpenCV would allocate the claim before finding the data short
    raise SljaxError(f"{path}: {problem}")
  return height, width


def _chunk_overrun(f: BinaryIO, size: int) -> str | None:
  """Why a PNG's chunks do not fit in its file (a length claiming more bytes than follow it),
  from their 8-byte headers alone; None when each fits, up to IEND or the file's end."""
  pos = 8
  while pos + 8 <= size:
    f.seek(pos)
    length, kind = struct.unpack(">I4s", f.read(8))
    if pos + 12 + length > size:
      return (f"truncated: chunk {kind.decode('latin-1')!r} at byte {pos} claims {length} bytes, "
              f"the file has {size}")
    if kind == b"IEND":
      break
    pos += 12 + length
  return None


def _png_room_problem(f: BinaryIO, width: int, height: int) -> str | None:
  """Why a PNG cannot hold the width x height its header claims (its file is smaller than its
  image data, inflated, compresses to at best); None when it can, or for another format."""
  f.seek(0)
  head = f.read(26)
  size = os.fstat(f.fileno()).st_size
  if head[:8] != PNG_SIGNATURE or len(head) < 26:
    return None
  overrun = _chunk_overrun(f, size)
  if overrun is not None:  # OpenCV allocates and reads what a chunk's length claims
    return overrun
  depth, colour = head[24], head[25]
  samples = _PNG_COLOURS.get(colour, (1, ()))[0]
  bits = depth * samples if depth in (1, 2, 4, 8, 16) else 1  # unknown: the smallest
  inflated = height * (1 + -(-width * bits // 8))
  if inflated <= DEFLATE_MAX_RATIO * size:
    return None
  return (f"corrupt: its header claims {width}x{height} pixels, whose image data cannot fit in "
          f"a file of {size} bytes")


# ----------------------------------------------------------------------------- PNG, whole


def png_chunks(data: bytes) -> tuple[tuple[int, ...], list[bytes]]:
  """((width, height, bit depth, colour type, interlace, whether PLTE is there), IDAT chunks)
  of a PNG whose chunk structure and CRCs are intact; ValueError naming the problem."""
  if data[:8] != PNG_SIGNATURE:
    raise ValueError("not a PNG file")
  pos, n, ihdr, idat, plte = 8, len(data), None, [], False
  while True:
    if pos + 8 > n:
      raise ValueError(f"truncated after {pos} bytes (no IEND chunk)")
    length, kind = struct.unpack(">I4s", data[pos:pos + 8])
    end = pos + 12 + length
    if end > n:
      raise ValueError(f"truncated: chunk {kind.decode('latin-1')} at byte {pos} needs {end} "
                       f"bytes, the file has {n}")
    body = data[pos + 4:pos + 8 + length]  # type + data, what the CRC covers
    if zlib.crc32(body) != struct.unpack(">I", data[pos + 8 + length:end])[0]:
      raise ValueError(f"corrupt: chunk {kind.decode('latin-1')} at byte {pos} fails its CRC "
                       "check")
    if ihdr is None:
      if kind != b"IHDR" or length < 13:
        raise ValueError("corrupt: the first chunk is not IHDR")
      ihdr = struct.unpack(">IIBBBBB", data[pos + 8:pos + 21])
    if kind == b"IDAT":
      idat.append(body[4:])
    plte |= kind == b"PLTE"
    pos = end
    if kind == b"IEND":
      break
  if not idat:
    raise ValueError("corrupt: no image data (IDAT)")
  width, height, depth, colour, _, _, interlace = ihdr
  return (width, height, depth, colour, interlace, plte), idat


def _rows(width: int, height: int, bits: int, interlace: int) -> list[tuple[int, int]]:
  """(rows, bytes per row including the filter byte) of each pass of the image data."""
  passes = _ADAM7 if interlace else ((0, 0, 1, 1),)
  out = []
  for y0, x0, dy, dx in passes:
    rows, cols = -(-(height - y0) // dy), -(-(width - x0) // dx)
    if rows > 0 and cols > 0:
      out.append((rows, 1 + -(-cols * bits // 8)))
  return out


def _inflate(idat: list[bytes], rows: list[tuple[int, int]]) -> None:
  """Inflates the image data as far as the header needs it, checking each row's filter type;
  ValueError for a broken zlib stream, too little data or an unknown filter."""
  need = sum(r * stride for r, stride in rows)
  starts = []  # (first byte, stride, rows) of each pass's filter bytes
  at = 0
  for r, stride in rows:
    starts.append((at, stride, r))
    at += r * stride
  d, got, pending = zlib.decompressobj(), 0, b"".join(idat)
  while got < need:
    try:
      out = d.decompress(pending, _INFLATE_STEP)
    except zlib.error as e:
      raise ValueError(f"corrupt: the image data does not inflate ({e}) after {got} of "
                       f"{need} bytes") from None
    pending = d.unconsumed_tail
    for first, stride, r in starts:  # filter bytes in [got, got + len(out))
      lo = max(0, -(-(got - first) // stride))
      hi = min(r, -(-(got + len(out) - first) // stride))
      for k in range(lo, hi):
        if out[first + k * stride - got] > 4:
          raise ValueError(f"corrupt: row {k} has filter type {out[first + k * stride - got]} "
                           "(0-4 exist)")
    got += len(out)
    if not out and not pending:
      raise ValueError(f"corrupt: the image data ends after {got} of {need} bytes")


def png_check(data: bytes) -> tuple[int, int, int]:
  """(width, height, bit depth) of a PNG whose chunks, CRCs, size and compressed image data are
  intact (the data inflated, not unfiltered); ValueError naming the problem."""
  (width, height, depth, colour, interlace, plte), idat = png_chunks(data)
  problem = pixel_problem(width, height)
  if problem is not None:  # before a byte is inflated
    raise ValueError(problem)
  if colour not in _PNG_COLOURS or depth not in _PNG_COLOURS[colour][1]:
    raise ValueError(f"corrupt: colour type {colour} with bit depth {depth}")
  if colour == 3 and not plte:
    raise ValueError("corrupt: a palette image without a palette (PLTE)")
  if interlace > 1:
    raise ValueError(f"corrupt: interlace method {interlace}")
  _inflate(idat, _rows(width, height, depth * _PNG_COLOURS[colour][0], interlace))
  return width, height, depth
