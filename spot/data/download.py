"""The HTTP transfer of ``spot data fetch``: one file from one URL into ``<path>.part``, capped.

The server is not trusted (issue 43). Bytes are counted while they stream and capped at
:attr:`Pin.cap` (the pinned size, else the size the lock file recorded, else the entry's
``max_size``, else ``Limits.max_bytes``): an endless body stops one byte past the cap. Every wait
has a limit (:class:`Limits`: connect and per-read timeouts, a minimum rate over a window, a
deadline per URL), and the message names the host and the bytes received so far. A dropped,
stalled or too slow connection is resumed with an HTTP Range request, ``retries`` times.
Redirects are followed by hand, at most ``max_redirects``: to the same origin, or to https on the
same host or on a host the registry declares (:func:`spot.data.sources.declared_hosts`); never to
another scheme, and never to a private, loopback, link-local, multicast or reserved address
unless it is the very origin the user named (``--mirror``, or a URL in the user's own
``--registry`` file).

:func:`download_to` raises :class:`Mismatch` (the bytes or the answer failed a check; the caller
deletes the partial file), :class:`Refused` (a redirect or address the :class:`Policy` does not
allow) or :class:`Unreachable` (HTTP errors, connections that keep failing; the partial file is
kept). Checking the sum and keeping or deleting the partial file is :mod:`spot.data.fetch`'s.
"""

from __future__ import annotations

import ipaddress
import socket
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urljoin, urlsplit

from spot import SpotError

PART_SUFFIX = ".part"
_NET_CHUNK = 1 << 16  # bytes per network read: what a dropped connection can lose before a resume
DEFAULT_MAX_BYTES = 8 << 30  # cap for a file with no pinned size, no recorded size and no max_size
MAX_REDIRECTS = 5
_PORTS = {"http": 80, "https": 443}


@dataclass(frozen=True)
class Limits:
    """How long and how much one file's download from one URL may take."""

    connect_timeout: float = 30.0  # seconds to open a connection
    read_timeout: float = 60.0  # seconds one socket read may wait (the answer, or more of the body)
    deadline: float | None = 4 * 3600.0  # seconds for the whole download, retries included; None: none
    min_rate: float = 1024.0  # bytes per second, averaged over each rate_window; 0: no check
    rate_window: float = 60.0
    max_bytes: int = DEFAULT_MAX_BYTES  # cap where no size is pinned, recorded or declared
    max_redirects: int = MAX_REDIRECTS

    def check(self) -> None:
        for key in ("connect_timeout", "read_timeout", "rate_window"):
            if not (getattr(self, key) > 0):  # also refuses NaN
                raise SpotError(f"fetch '{key}' is {getattr(self, key)!r}; expected a positive number of seconds")
        if self.deadline is not None and not self.deadline > 0:
            raise SpotError(f"fetch 'deadline' is {self.deadline!r}; expected positive seconds or None")
        if not self.min_rate >= 0:
            raise SpotError(f"fetch 'min_rate' is {self.min_rate!r}; expected bytes per second >= 0")
        if not (self.max_bytes >= 1 and 0 <= self.max_redirects <= 30):
            raise SpotError(
                f"fetch 'max_bytes' {self.max_bytes!r} / 'max_redirects' {self.max_redirects!r}: "
                "expected >= 1 byte and 0-30 redirects"
            )


class Mismatch(Exception):
    """A URL served something that failed verification (deleted; try the next URL)."""


class Refused(Mismatch):
    """A redirect or an address that the policy does not allow."""


class Unreachable(Exception):
    """A URL could not deliver the file (HTTP error, connection failures past the retries)."""


class _Retry(Exception):
    """A dropped, stalled or too slow transfer: resumed, unless ``final`` (the deadline passed)."""

    def __init__(self, message: str, final: bool = False):
        super().__init__(message)
        self.final = final


@dataclass(frozen=True)
class Pin:
    """What one file's download is checked against (:mod:`spot.data.fetch` makes it from the registry
    and the lock file)."""

    sha: str | None  # None: trust on first use, nothing recorded yet
    size: int | None
    by: str  # the trust the sum comes from
    cap: int  # no more bytes than this are ever written
    cap_what: str


# --------------------------------------------------------------------------- where a request may go
@dataclass(frozen=True)
class Policy:
    """Where this fetch's requests may go, and its :class:`Limits`."""

    hosts: frozenset[str]  # hosts (or '*.domain') a redirect may go to over https
    explicit: frozenset[tuple[str, str, int]]  # origins the user named: any address allowed
    limits: Limits


def origin_of(url: str) -> tuple[str, str, int]:
    """(scheme, host, port) of ``url``; ValueError for a port that is not a number."""
    parts = urlsplit(url)
    scheme = parts.scheme.lower()
    return scheme, (parts.hostname or "").lower(), parts.port or _PORTS.get(scheme, 0)


def short(text: str, n: int = 200) -> str:
    """A server-chosen string made safe for a one-line message: printable ASCII, at most n chars."""
    clean = "".join(c if " " <= c <= "~" else "?" for c in str(text))
    return clean if len(clean) <= n else clean[:n] + "..."


def _declared(host: str, patterns: frozenset[str]) -> bool:
    return any(host == p or (p.startswith("*.") and host.endswith(p[1:])) for p in patterns)


def _redirect_target(current: str, location: str, policy: Policy) -> str:
    """The URL a redirect from ``current`` to ``location`` leads to, if the policy allows it."""
    target = urljoin(current, location.strip())
    try:
        new, cur = origin_of(target), origin_of(current)
    except ValueError:
        raise Refused(f"redirect to '{short(target)}' refused: not a valid URL") from None
    if new[0] not in _PORTS:
        raise Refused(f"redirect to '{short(target)}' refused: scheme '{short(new[0], 20)}:' (only http(s))")
    if new == cur:
        return target  # same scheme, host and port: another path on the server already asked
    if new[0] != "https":
        raise Refused(f"redirect to '{short(target)}' refused: plain http to another origin than {cur[1]}:{cur[2]}")
    if new[1] != cur[1] and not _declared(new[1], policy.hosts):
        raise Refused(
            f"redirect to '{short(target)}' refused: host {short(new[1], 80)} is neither {cur[1]} "
            "nor a host the sources registry declares"
        )
    return target


def _resolve(host: str, port: int) -> list[ipaddress.IPv4Address | ipaddress.IPv6Address]:
    try:
        return [ipaddress.ip_address(host)]
    except ValueError:
        pass
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except (OSError, UnicodeError) as err:
        raise Unreachable(f"cannot resolve host {short(host, 80)} ({err})") from None
    return [ipaddress.ip_address(str(info[4][0]).split("%")[0]) for info in infos]


def _not_public(ip: ipaddress.IPv4Address | ipaddress.IPv6Address) -> str:
    """'' for a public unicast address, else what it is (loopback, link-local, ...)."""
    if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped:
        ip = ip.ipv4_mapped
    for kind in ("loopback", "link_local", "multicast", "private", "reserved", "unspecified"):
        if getattr(ip, f"is_{kind}"):
            return kind.replace("_", "-")
    return "" if ip.is_global else "non-public"


def _check_address(url: str, policy: Policy) -> None:
    """Refuse a URL whose host resolves to a non-public address, unless the user named that origin."""
    origin = origin_of(url)
    if origin in policy.explicit:
        return
    for ip in _resolve(origin[1], origin[2]):
        if kind := _not_public(ip):
            raise Refused(
                f"'{short(url)}' refused: {short(origin[1], 80)} resolves to {ip}, a {kind} address; only "
                "an origin the user named (--mirror or their own --registry) may be one"
            )


def _check_peer(r: Any, url: str, policy: Policy) -> None:
    """The address actually connected to must pass too (a name that resolved again elsewhere)."""
    import requests

    origin = origin_of(url)
    if origin in policy.explicit or requests.utils.get_environ_proxies(url):
        return  # the user's own origin, or a proxy the user set up connects for us
    try:
        ip = ipaddress.ip_address(str(r.raw.connection.sock.getpeername()[0]).split("%")[0])
    except (AttributeError, OSError, ValueError, IndexError, TypeError):
        return  # no socket to ask (closed already): the resolution check stands
    if kind := _not_public(ip):
        raise Refused(
            f"'{short(url)}' refused: the connection to {short(origin[1], 80)} went to {ip}, a {kind} address"
        )


# --------------------------------------------------------------------------- the transfer
class _Clock:
    """The deadline of one URL's download and the minimum-rate check; messages name the host."""

    def __init__(self, host: str, limits: Limits):
        self.host, self.limits = host, limits
        self.start = self.mark = time.monotonic()
        self.mark_bytes = 0

    def new_window(self, have: int) -> None:
        self.mark, self.mark_bytes = time.monotonic(), have

    def check(self, have: int, waiting_for: str) -> None:
        now, lim = time.monotonic(), self.limits
        if lim.deadline is not None and now - self.start > lim.deadline:
            raise _Retry(
                f"{self.host}: the download passed its deadline of {lim.deadline:g} s while waiting for "
                f"{waiting_for} ({have:,} bytes so far)",
                final=True,
            )
        span = now - self.mark
        if lim.min_rate and span >= lim.rate_window:
            got = have - self.mark_bytes
            if got < lim.min_rate * span:
                raise _Retry(
                    f"{self.host} sent {got:,} bytes in {span:.1f} s while we waited for {waiting_for}, below "
                    f"the minimum of {lim.min_rate:g} bytes/s ({have:,} bytes so far)"
                )
            self.new_window(have)


def download_to(
    url: str, part: Path, pin: Pin, policy: Policy, progress: bool, retries: int, backoff: float
) -> tuple[int, int | None]:
    """Download ``url`` into ``part``, resuming what it holds; return (size, announced size).

    Raises ``Unreachable`` for HTTP errors and connections that keep failing (the partial file
    is kept), ``Mismatch`` when the server announces or sends another size than allowed, and
    ``Refused`` for a redirect or address the policy refuses.
    """
    import requests

    clock = _Clock(origin_of(url)[1], policy.limits)
    attempt, announced = 0, pin.size
    with requests.Session() as session:
        while True:
            have = part.stat().st_size if part.exists() else 0
            if have > pin.cap:
                part.unlink()
                have = 0
            try:
                clock.new_window(have)
                r = _open(session, url, have, policy, clock)
                with r:
                    if r.status_code == 416 and have:
                        if pin.size is not None and have == pin.size:
                            break  # the partial file is already complete
                        part.unlink()  # the server has no bytes past what we hold: start over
                        raise _Retry(f"HTTP 416 for a resume at byte {have}")
                    total = _receive(r, part, have, pin, clock, progress)
                announced = announced if announced is not None else total
                break
            except _Retry as err:
                attempt += 1
                if err.final:
                    raise Unreachable(str(err)) from None
                if attempt > retries:
                    raise Unreachable(f"connection failed {attempt} times (last: {err})") from None
                time.sleep(backoff * 2 ** (attempt - 1))
    got = part.stat().st_size
    if announced is not None and got != announced:
        raise Mismatch(f"got {got} bytes; the server announced {announced}")
    return got, announced


def _open(session: Any, url: str, have: int, policy: Policy, clock: _Clock) -> Any:
    """GET ``url`` (from byte ``have``), following the redirects the policy allows."""
    import requests

    lim = policy.limits
    headers = {"Accept-Encoding": "identity", **({"Range": f"bytes={have}-"} if have else {})}
    current = url
    for _ in range(lim.max_redirects + 1):
        clock.check(have, "an answer")
        _check_address(current, policy)
        clock.host = short(origin_of(current)[1], 80)
        try:
            r = session.get(
                current,
                headers=headers,
                stream=True,
                allow_redirects=False,
                timeout=(lim.connect_timeout, lim.read_timeout),
            )
        except requests.ConnectTimeout:
            raise _Retry(f"no connection to {clock.host} within {lim.connect_timeout:g} s") from None
        except requests.ReadTimeout:
            raise _Retry(f"{clock.host} sent no answer within {lim.read_timeout:g} s") from None
        except requests.ConnectionError as err:
            raise _Retry(f"connection to {clock.host} failed ({type(err).__name__}: {short(err)})") from None
        except requests.RequestException as err:
            raise Unreachable(f"{type(err).__name__}: {short(err)}") from None
        if not r.is_redirect:
            try:
                _check_peer(r, current, policy)
            except Refused:
                r.close()
                raise
            return r
        r.close()
        current = _redirect_target(current, r.headers.get("Location", ""), policy)
    raise Refused(f"more than {lim.max_redirects} redirects (the last to '{short(current)}')")


def _receive(r: Any, part: Path, have: int, pin: Pin, clock: _Clock, progress: bool) -> int | None:
    """Write the body of ``r`` to ``part`` from byte ``have``, at most ``pin.cap`` bytes in all;
    return the size the server announced (None when it did not)."""
    host = clock.host
    if r.status_code not in (200, 206):
        raise Unreachable(f"HTTP {r.status_code} {short(r.reason, 80)}")
    encoding = r.headers.get("Content-Encoding", "identity").strip().lower()
    if encoding not in ("", "identity"):
        raise Mismatch(f"{host} sent the file with Content-Encoding '{short(encoding, 40)}' (identity was asked)")
    total = _announced_total(r, have)
    if pin.size is not None and total is not None and total != pin.size:
        raise Mismatch(f"the server announces {total} bytes; expected {pin.size}")
    if total is not None and total > pin.cap:
        raise Mismatch(f"{host} announces {total:,} bytes, more than {pin.cap:,} ({pin.cap_what})")
    mode = "ab"
    if r.status_code == 200 and have:
        mode, have = "wb", 0  # the server ignored the Range header: start over
    elif r.status_code == 206 and not _range_starts_at(r, have):
        raise Unreachable(f"server answered Range bytes={have}- with '{short(r.headers.get('Content-Range'))}'")
    with _bar(pin.size or total, have, part, progress) as bar, open(part, mode) as fh:
        while chunk := _read(r, have, pin.cap + 1 - have, clock):
            if have + len(chunk) > pin.cap:
                raise Mismatch(
                    f"{host} sent more than {pin.cap:,} bytes ({pin.cap_what}); stopped at {have + len(chunk):,}"
                )
            fh.write(chunk)
            have += len(chunk)
            bar.update(len(chunk))
            clock.check(have, "the rest of the file")
    return total


def _read(r: Any, have: int, most: int, clock: _Clock) -> bytes:
    """What the server has sent so far, up to ``most`` bytes: returns as soon as any bytes came, so
    a trickle cannot hold the deadline and rate checks off (each wait is ``read_timeout`` at most)."""
    from urllib3.exceptions import HTTPError, ReadTimeoutError

    try:
        return r.raw.read1(min(_NET_CHUNK, most), decode_content=False) or b""
    except ReadTimeoutError:
        raise _Retry(f"{clock.host} sent nothing for {clock.limits.read_timeout:g} s ({have:,} bytes so far)") from None
    except (HTTPError, OSError) as err:
        why = (
            "the body ended before the length it announced"
            if "IncompleteRead" in repr(err)
            else f"{type(err).__name__}: {short(err, 120)}"
        )
        raise _Retry(f"{clock.host} broke off after {have:,} bytes ({why})") from None


def _bar(total: int | None, have: int, part: Path, progress: bool) -> Any:
    from tqdm.auto import tqdm

    return tqdm(
        total=total,
        initial=have,
        unit="B",
        unit_scale=True,
        unit_divisor=1024,
        desc=part.name[: -len(PART_SUFFIX)],
        disable=not progress,
        leave=False,
    )


def _announced_total(r: Any, have: int) -> int | None:
    if r.status_code == 206:
        cr = r.headers.get("Content-Range", "")
        tail = cr.rsplit("/", 1)[-1] if "/" in cr else ""
        return int(tail) if tail.isdigit() else None
    length = r.headers.get("Content-Length")
    return int(length) if length and length.isdigit() else None


def _range_starts_at(r: Any, have: int) -> bool:
    cr = r.headers.get("Content-Range", "")  # "bytes START-END/TOTAL"
    try:
        return int(cr.split()[1].split("-")[0]) == have
    except (IndexError, ValueError):
        return False
