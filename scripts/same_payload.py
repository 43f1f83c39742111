#!/usr/bin/env python3
"""Whether two checkpoints hold the same field to the byte: compares what
follows the metadata (coordinates, density, SH, optimiser state), so runs
whose metadata differ (paths, seconds, a newer metadata layout) can be
checked for the same bits. Reads safetensors checkpoints and the bincode
files (tag REFNPRG1) written before; both files must be of one kind.

    python3 scripts/same_payload.py A/checkpoint.bin B/checkpoint.bin    # exit 0: the same payload
"""
import hashlib
import struct
import sys

MAGIC = b"REFNPRG1"


def payload(path):
    data = open(path, "rb").read()
    if data[:8] == MAGIC:
        (length,) = struct.unpack("<Q", data[8:16])
        return data[16 + length:]
    (length,) = struct.unpack("<Q", data[:8])
    if length > len(data) - 8 or data[8:9] != b"{":
        sys.exit(f"{path} is not a refnpr checkpoint")
    # safetensors: the tensors' bytes follow the JSON header (the same
    # shapes give the same offsets, so equal bytes are equal arrays).
    return data[8 + length:]


def main():
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    a, b = payload(sys.argv[1]), payload(sys.argv[2])
    digest = lambda x: hashlib.sha256(x).hexdigest()[:16]
    same = a == b
    print(f"{'SAME' if same else 'DIFFERENT'} payload: {len(a)} / {len(b)} bytes, sha256 {digest(a)} / {digest(b)}")
    sys.exit(0 if same else 1)


if __name__ == "__main__":
    main()
