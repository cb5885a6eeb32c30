"""MCAP recordings of a run: the layout (layout.py), writing (writer.py) and the recorder's loop (recorder.py),
reading a possibly cut file (reader.py) within bounds and checksums (integrity.py), comparing contents (compare.py)
and replaying them over Zenoh (player.py)."""

from .compare import content_signature
from .layout import BACKFILL_METADATA, CHUNK_MESSAGES, FLUSH_INTERVAL_S, INVALID_KEY, METADATA_NAME, versions
from .player import Player, PlayStats, select
from .reader import ChannelInfo, RecordedMessage, Recording, RecordingError, read_recording
from .recorder import Recorder
from .writer import RecordingWriter, read_attachments

__all__ = ["BACKFILL_METADATA", "CHUNK_MESSAGES", "FLUSH_INTERVAL_S", "INVALID_KEY", "METADATA_NAME", "ChannelInfo", "PlayStats", "Player",
           "RecordedMessage", "Recorder", "Recording", "RecordingError", "RecordingWriter", "content_signature",
           "read_attachments", "read_recording", "select", "versions"]
