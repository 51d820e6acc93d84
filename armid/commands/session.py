"""The Zenoh session of a command (``--zenoh-listen``, ``--zenoh-connect``, ``--zenoh-config``):
a configuration that cannot be read or opened is bad input (exit 2)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from armid.schema.errors import InputFileError, OptionError

from .output import one_line


def _zenoh_message(err: BaseException) -> str:
    """Zenoh's error text without its Rust source locations, on one line."""
    import re

    text = str(err)
    inner = re.search(r'msg: "(.*?)(?: at /[^"]*)?"', text)
    text = inner.group(1) if inner else re.sub(r" at /\S+\.rs:\d+\.?", "", text)
    return one_line(text, 200)


def open_zenoh(args: argparse.Namespace) -> Any:
    """A Zenoh session from the command's options; a configuration file that cannot be read,
    names a certificate that is not there, or cannot open a session is bad input (exit 2)."""
    import zenoh

    from armid.daq.stream import session_config

    src = args.zenoh_config
    endpoints = "--zenoh-listen/--zenoh-connect"
    if src is None and args.zenoh_listen is None and args.zenoh_connect is None:
        from armid.daq.stream import local_endpoint, open_local_session

        try:  # no flags: find the other armid processes on this machine (daq.stream.open_local_session)
            return open_local_session()
        except Exception as err:
            raise OptionError(endpoints, f"no endpoint given and the local one {local_endpoint()} cannot be used "
                                         f"({_zenoh_message(err)})") from None
    if src is not None and not Path(src).is_file():
        raise InputFileError(src, "", "no such file")
    try:
        config = session_config(args.zenoh_listen, args.zenoh_connect, src)
    except Exception as err:  # zenoh raises ZError for syntax, schema and endpoints alike
        if src is not None:
            raise InputFileError(src, "", f"not a usable Zenoh configuration ({_zenoh_message(err)})") from None
        raise OptionError(endpoints, _zenoh_message(err)) from None
    if src is not None:
        try:
            tls = json.loads(config.get_json("transport/link/tls"))
        except Exception:
            tls = {}
        for name, value in (tls or {}).items():
            if isinstance(value, str) and name.endswith(("_certificate", "_private_key")) and not Path(value).is_file():
                raise InputFileError(src, f"transport.link.tls.{name}", f"no such file {value}")
    try:
        return zenoh.open(config)
    except Exception as err:
        raise InputFileError(src or endpoints, "", f"cannot open a Zenoh session ({_zenoh_message(err)})") from None


def add_zenoh_arguments(p: argparse.ArgumentParser) -> None:
    """Where the Zenoh session connects (peer mode, multicast scouting off). With none of
    these, armid processes on one machine find each other (``daq.stream.open_local_session``)."""
    p.add_argument("--zenoh-listen", nargs="*", metavar="ENDPOINT", help="Zenoh endpoints to listen on, e.g. tcp/127.0.0.1:7447")
    p.add_argument("--zenoh-connect", nargs="*", metavar="ENDPOINT", help="Zenoh endpoints to connect to")
    p.add_argument("--zenoh-config", metavar="JSON5", help="a Zenoh configuration file (config/zenoh/lab.json5)")
