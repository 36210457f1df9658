"""The search for a forgotten person's id over a record folder (docs/privacy.md): the state
store's files as bytes, every bag record by record with its zstd chunks decompressed."""
import json
from pathlib import Path

from mcap.records import Chunk
from mcap.stream_reader import StreamReader, get_chunk_data_stream


def id_forms(user_id: str) -> list:
    """How the id lies in the files: plain, JSON-escaped, and as a CDR string."""
    plain = user_id.encode()
    return [plain, json.dumps(user_id)[1:-1].encode(), (len(plain) + 1).to_bytes(4, 'little') + plain + b'\0']


def store_bytes(folder: Path) -> dict:
    """{file name: bytes} of state.db and its -wal and -shm files, those that exist."""
    return {name: (folder / name).read_bytes() for name in ('state.db', 'state.db-wal', 'state.db-shm')
            if (folder / name).exists()}


def bag_records(folder: Path) -> list:
    """The bytes of every record of every MCAP file under ``folder``, each chunk's records
    decompressed too (a zstd chunk hides its content from a raw byte search)."""
    found = []
    for path in sorted(folder.rglob('*.mcap')):
        with open(path, 'rb') as handle:
            for record in StreamReader(handle, emit_chunks=True).records:
                if isinstance(record, Chunk):
                    stream, length = get_chunk_data_stream(record, validate_crc=True)
                    found += _records_in(stream.read(length))
                else:
                    found.append(repr(vars(record)).encode('utf-8', 'backslashreplace') +
                                 bytes(getattr(record, 'data', b'') or b''))
    return found


def _records_in(data: bytes) -> list:
    """The records of a chunk's content: opcode, uint64 length, body."""
    records, at = [], 0
    while at < len(data):
        length = int.from_bytes(data[at + 1:at + 9], 'little')
        records.append(data[at:at + 9 + length])
        at += 9 + length
    return records


def holds(data: bytes, user_id: str, others=('p21', 'ann-7')) -> bool:
    """``user_id`` in ``data`` in any of its forms, as a plain byte search (the ids of
    others that hold it, ``p21``, taken out first)."""
    for other in others:
        for form in id_forms(other):
            data = data.replace(form, b'')
    return any(form in data for form in id_forms(user_id))
