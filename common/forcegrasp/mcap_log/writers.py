"""MCAP writer backends: foxglove-sdk's fast writer, or the pure-Python ``mcap`` package."""

from __future__ import annotations

from pathlib import Path

from mcap.writer import CompressionType, Writer


class _PlainWriter:
    """The ``mcap`` package's pure-Python writer (always available)."""

    def __init__(self, path: Path, chunk_size: int):
        self._file = open(path, "wb")
        self._w = Writer(self._file, chunk_size=chunk_size, compression=CompressionType.ZSTD)
        self._w.start(profile="", library="forcegrasp")
        self._schemas: dict[str, int] = {}
        self._seq = 0

    def channel(self, topic: str, schema: str, schema_data: bytes):
        if schema not in self._schemas:
            self._schemas[schema] = self._w.register_schema(name=schema, encoding="jsonschema", data=schema_data)
        return self._w.register_channel(topic=topic, message_encoding="json", schema_id=self._schemas[schema])

    def write(self, channel, t_ns: int, data: bytes) -> None:
        self._w.add_message(channel_id=channel, log_time=t_ns, publish_time=t_ns, data=data, sequence=self._seq)
        self._seq += 1

    def metadata(self, name: str, data: dict[str, str]) -> None:
        self._w.add_metadata(name, data)

    def close(self) -> None:
        try:
            self._w.finish()
        finally:
            self._file.close()

    def discard(self) -> None:
        self._file.close()


class _SdkWriter:
    """foxglove-sdk's writer (Rust): about 3x less time per message than the pure-Python one.

    One private logging context per file, so episodes never mix; zstd level 1 (a third less
    time than the default level for ~10 % larger files) on the calling thread
    (``compression_threads=0``): the evaluator owns one core, it does not take another.
    """

    def __init__(self, path: Path, chunk_size: int):
        import foxglove
        from foxglove.mcap import MCAPCompression, MCAPWriteOptions

        self._fg = foxglove
        self._ctx = foxglove.Context()
        options = MCAPWriteOptions(compression=MCAPCompression.Zstd, compression_level=1, chunk_size=chunk_size,
                                   compression_threads=0, profile="")
        self._w = foxglove.open_mcap(str(path), allow_overwrite=True, context=self._ctx, writer_options=options)
        self._channels: list = []

    def channel(self, topic: str, schema: str, schema_data: bytes):
        ch = self._fg.Channel(topic, schema=self._fg.Schema(name=schema, encoding="jsonschema", data=schema_data),
                              message_encoding="json", context=self._ctx)
        self._channels.append(ch)
        return ch

    def write(self, channel, t_ns: int, data: bytes) -> None:
        channel.log(data, log_time=t_ns)

    def metadata(self, name: str, data: dict[str, str]) -> None:
        self._w.write_metadata(name, data)

    def close(self) -> None:
        for ch in self._channels:
            ch.close()
        self._w.close()

    def discard(self) -> None:
        self.close()


def writer_class(backend: str):
    if backend == "auto":
        try:
            import foxglove  # noqa: F401  (optional: foxglove-sdk)

            return _SdkWriter
        except ImportError:
            return _PlainWriter
    return {"sdk": _SdkWriter, "mcap": _PlainWriter}[backend]
