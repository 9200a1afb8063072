"""Reads an MCAP file with the `mcap` Python package (an independent reader) and prints
one JSON line: its profile, each channel's topic, encoding and schema, and the sequence
numbers of the messages, in file order."""
import json
import sys

from mcap.reader import make_reader


def main(path):
    with open(path, "rb") as f:
        reader = make_reader(f)
        header = reader.get_header()
        channels = {}
        sequences = []
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            channels[channel.id] = {
                "topic": channel.topic,
                "message_encoding": channel.message_encoding,
                "schema_name": schema.name if schema else "",
                "schema_encoding": schema.encoding if schema else "",
                "schema_bytes": len(schema.data) if schema else 0,
            }
            sequences.append(message.sequence)
    print(json.dumps({
        "profile": header.profile,
        "channels": list(channels.values()),
        "sequences": sequences,
    }))


if __name__ == "__main__":
    main(sys.argv[1])
