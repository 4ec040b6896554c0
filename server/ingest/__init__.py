"""Zenoh ingest: session, subscriber (decode thread), reorder buffers, counters, pipeline."""

from server.ingest.counters import IngestCounters
from server.ingest.pipeline import EstimateSink, Pipeline
from server.ingest.reorder import ReorderBuffer, Verdict
from server.ingest.subscriber import IngestSubscriber
from server.ingest.zenoh_session import make_config, open_session

__all__ = [
    "EstimateSink",
    "IngestCounters",
    "IngestSubscriber",
    "Pipeline",
    "ReorderBuffer",
    "Verdict",
    "make_config",
    "open_session",
]
