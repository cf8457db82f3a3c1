"""``reindex``: make a bag whose recording was killed whole again, as ``ros2 bag reindex``
does for rosbag2.

A killed recorder leaves ``<name>_<n>.mcap`` files without a summary and no
``metadata.yaml``. Streaming readers read such files (bag_writer seals every write), but
indexed readers (mcap's seeking reader with its chunk indexes) and rosbag2-style readers
(``rosbags``' AnyReader, ``ros2 bag info``) need the summary and the metadata. ``reindex``
rewrites every data file with a summary, keeping the split into files, each message's
bytes and times, each topic's QoS and type hash and the chunk compression, then writes
``metadata.yaml``.
What the crash cut off (the chunk being filled) is gone; everything flushed is kept.

Usage: ``reindex <bag directory>`` (exit status 0 = reindexed, 1 = not a bag or failed).
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
from collections.abc import Iterable, Sequence
from pathlib import Path

from mcap.exceptions import McapError
from mcap.records import Chunk
from mcap.stream_reader import StreamReader

from bag_tools.bag_writer import METADATA_FILENAME, BagError, BagReader, BagWriter


def reindex(bag_path: str | os.PathLike[str]) -> BagReader:
    """Rewrite ``bag_path``'s data files with summaries and write its ``metadata.yaml``;
    returns the new BagReader. Raises BagError if it is no bag or cannot be written."""
    bag_path = Path(bag_path)
    source = BagReader(bag_path)
    staging_root = bag_path.parent / f'.{bag_path.name}.reindex'
    shutil.rmtree(staging_root, ignore_errors=True)
    staging = staging_root / bag_path.name  # so the files keep the bag's name pattern
    try:
        writer = BagWriter(staging, compression=_chunk_compression(source.files))
        for topic in source.topics:
            writer.add_topic(
                topic.name,
                topic.type,
                topic.offered_qos_profiles,
                topic.type_description_hash or None,
            )
        for index, path in enumerate(source.files):
            if index:
                writer.split()
            for message in source.file_messages(path, cut_short_ok=True):
                writer.write(message.topic, message.data, message.log_time, message.publish_time)
        writer.close()
        # Data files first, metadata.yaml last: until it exists the bag still reads as a
        # recovered one.
        (bag_path / METADATA_FILENAME).unlink(missing_ok=True)
        for path in source.files:
            path.unlink()
        for path in writer.file_paths:
            os.replace(path, bag_path / path.name)
        os.replace(staging / METADATA_FILENAME, bag_path / METADATA_FILENAME)
    finally:
        shutil.rmtree(staging_root, ignore_errors=True)
    return BagReader(bag_path)


def _chunk_compression(paths: Iterable[Path]) -> str:
    """The compression of the first chunk of the first of ``paths`` that has one ('' if
    none), read front to back as far as a crash left it."""
    for path in paths:
        with open(path, 'rb') as stream:
            try:
                for record in StreamReader(stream, emit_chunks=True).records:
                    if isinstance(record, Chunk):
                        return record.compression
            except (McapError, EOFError, ValueError):
                pass  # a tail cut short, or no chunk before it
    return ''


def main(argv: Sequence[str] | None = None) -> int:
    """The ``reindex`` command: reindex the bag directory named in ``argv`` and print its
    topics' message counts; returns the exit status (0 = reindexed, 1 = not a bag or
    failed)."""
    parser = argparse.ArgumentParser(
        prog='reindex',
        description='Rebuild the summary and metadata.yaml of a bag whose '
        'recording was killed (as ros2 bag reindex).',
    )
    parser.add_argument('bag', help='the bag directory')
    args = parser.parse_args(argv)
    try:
        bag = reindex(args.bag)
    except (BagError, OSError) as error:
        print(f'reindex: {error}', file=sys.stderr)
        return 1
    counts = ', '.join(f'{t.name}={t.message_count}' for t in bag.topics)
    print(
        f'reindexed {args.bag}: {bag.message_count} messages in {len(bag.files)} '
        f'file(s) ({counts})'
    )
    return 0


if __name__ == '__main__':
    sys.exit(main())
