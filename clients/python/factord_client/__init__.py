"""Python client for factord: HTTP (:class:`HttpClient`, standard library only), zenoh
(:class:`ZenohClient`, needs ``eclipse-zenoh``) and a small g2o reader (:mod:`factord_client.g2o`)
that turns a dataset into the batches a robot would stream."""

from .errors import BatchRefused, FactordConnectionError, FactordError, FactordTimeout
from .http import EventStream, HttpClient
from .producer import HttpProducer

__all__ = [
    "BatchRefused",
    "EventStream",
    "FactordConnectionError",
    "FactordError",
    "FactordTimeout",
    "HttpClient",
    "HttpProducer",
    "StreamProducer",
    "ZenohClient",
]
__version__ = "0.1.0"


def __getattr__(name: str):  # lazy: importing the package must not need zenoh
    if name == "ZenohClient":
        from .zenoh_client import ZenohClient

        return ZenohClient
    if name == "StreamProducer":
        from .stream_producer import StreamProducer

        return StreamProducer
    raise AttributeError(name)
