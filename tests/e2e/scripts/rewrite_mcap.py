"""Writes an MCAP file again with the `mcap` Python package (an independent writer):
every schema, channel and message of IN, in file order, into OUT, in chunks of at most
CHUNK bytes compressed with COMPRESSION (zstd, lz4 or none)."""
import sys

from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer


def main(src, dst, compression, chunk):
    kind = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
    with open(src, "rb") as f, open(dst, "wb") as out:
        reader = make_reader(f)
        header = reader.get_header()
        writer = Writer(out, chunk_size=int(chunk), compression=kind[compression])
        writer.start(profile=header.profile, library="python mcap")
        schemas, channels = {}, {}
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            if schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schemas[schema.id], channel.metadata
                )
            writer.add_message(
                channels[channel.id],
                message.log_time,
                message.data,
                message.publish_time,
                message.sequence,
            )
        writer.finish()


if __name__ == "__main__":
    main(*sys.argv[1:5])
