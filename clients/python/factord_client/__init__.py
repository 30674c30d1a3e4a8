"""Python client for factord: HTTP (:class:`HttpClient`, standard library only), zenoh
(:class:`ZenohClient`, needs ``eclipse-zenoh``) and a small g2o reader (:mod:`factord_client.g2o`)
that turns a dataset into the batches a robot would stream."""

from .errors import FactordError
from .http import EventStream, HttpClient

__all__ = ["FactordError", "HttpClient", "EventStream", "ZenohClient"]
__version__ = "0.1.0"


def __getattr__(name: str):  # lazy: importing the package must not need zenoh
    if name == "ZenohClient":
        from .zenoh_client import ZenohClient

        return ZenohClient
    raise AttributeError(name)
