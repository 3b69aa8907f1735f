"""MJPEG as UVC cameras send it, made into standalone JPEG files: the JPEG inside a padded
driver buffer, its header (size, whether it carries Huffman tables), and the standard tables
that many cameras leave out."""

from __future__ import annotations

from dataclasses import dataclass

SOI = b"\xff\xd8"
EOI = b"\xff\xd9"
_SOF_MARKERS = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
_STANDALONE = {0x01, *range(0xD0, 0xD8)}   # markers without a length field


@dataclass(frozen=True)
class JpegHeader:
    width: int
    height: int
    has_huffman: bool
    sos_offset: int      # where the scan's SOS marker starts


def jpeg_trim(buf: bytes) -> bytes | None:
    """The JPEG inside a driver buffer: SOI .. last EOI (drivers pad buffers); None if there is none."""
    if not buf.startswith(SOI):
        return None
    end = buf.rfind(EOI)
    if end < 2:
        return None
    return buf[:end + 2]


def jpeg_header(jpeg: bytes) -> JpegHeader | None:
    """Walk the marker segments up to the scan; None when they do not parse."""
    pos, width, height, has_huffman = 2, None, None, False
    while pos + 4 <= len(jpeg):
        if jpeg[pos] != 0xFF:
            return None
        marker = jpeg[pos + 1]
        if marker == 0xFF:          # fill byte
            pos += 1
            continue
        if marker in _STANDALONE:
            pos += 2
            continue
        length = int.from_bytes(jpeg[pos + 2:pos + 4], "big")
        if length < 2 or pos + 2 + length > len(jpeg):
            return None
        if marker == 0xDA:
            if width is None:
                return None
            return JpegHeader(width, height, has_huffman, pos)
        if marker == 0xC4:
            has_huffman = True
        elif marker in _SOF_MARKERS and length >= 7:
            height = int.from_bytes(jpeg[pos + 5:pos + 7], "big")
            width = int.from_bytes(jpeg[pos + 7:pos + 9], "big")
        pos += 2 + length
    return None


def _table(cls_id: int, counts: list[int], first: list[int], symbols: list[int]) -> bytes:
    # The last code length holds every symbol not listed before it, in increasing order.
    values = first + sorted(set(symbols) - set(first))
    assert len(values) == sum(counts)
    return bytes([cls_id, *counts, *values])


def _standard_dht() -> bytes:
    """The DHT segment of the typical tables of ITU-T T.81 Annex K.3, which MJPEG streams that
    omit their tables are decoded with (the AVI MJPEG convention)."""
    ac_symbols = [0x00, 0xF0] + [run << 4 | size for run in range(16) for size in range(1, 11)]
    dc_lum = bytes([0x00, 0, 1, 5, 1, 1, 1, 1, 1, 1, 0, 0, 0, 0, 0, 0, 0, *range(12)])
    dc_chrom = bytes([0x01, 0, 3, 1, 1, 1, 1, 1, 1, 1, 1, 1, 0, 0, 0, 0, 0, *range(12)])
    ac_lum = _table(0x10, [0, 2, 1, 3, 3, 2, 4, 3, 5, 5, 4, 4, 0, 0, 1, 0x7D],
                    [0x01, 0x02, 0x03, 0x00, 0x04, 0x11, 0x05, 0x12, 0x21, 0x31, 0x41, 0x06, 0x13,
                     0x51, 0x61, 0x07, 0x22, 0x71, 0x14, 0x32, 0x81, 0x91, 0xA1, 0x08, 0x23, 0x42,
                     0xB1, 0xC1, 0x15, 0x52, 0xD1, 0xF0, 0x24, 0x33, 0x62, 0x72, 0x82], ac_symbols)
    ac_chrom = _table(0x11, [0, 2, 1, 2, 4, 4, 3, 4, 7, 5, 4, 4, 0, 1, 2, 0x77],
                      [0x00, 0x01, 0x02, 0x03, 0x11, 0x04, 0x05, 0x21, 0x31, 0x06, 0x12, 0x41, 0x51,
                       0x07, 0x61, 0x71, 0x13, 0x22, 0x32, 0x81, 0x08, 0x14, 0x42, 0x91, 0xA1, 0xB1,
                       0xC1, 0x09, 0x23, 0x33, 0x52, 0xF0, 0x15, 0x62, 0x72, 0xD1, 0x0A, 0x16, 0x24,
                       0x34, 0xE1, 0x25, 0xF1], ac_symbols)
    body = dc_lum + ac_lum + dc_chrom + ac_chrom
    return b"\xff\xc4" + (len(body) + 2).to_bytes(2, "big") + body


STANDARD_DHT = _standard_dht()


def with_huffman_tables(jpeg: bytes, header: JpegHeader) -> bytes:
    """The JPEG as a standalone file: the standard tables inserted before the scan if absent."""
    if header.has_huffman:
        return jpeg
    return jpeg[:header.sos_offset] + STANDARD_DHT + jpeg[header.sos_offset:]
