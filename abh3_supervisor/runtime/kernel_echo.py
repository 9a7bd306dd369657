"""Our own ``udp_multicast`` datagrams dropped by the kernel, before they are queued to us.

A group member receives every datagram sent to the group, its own too (the loopback
delivers them within the ``sendto``), and the socket has no option against it. The
:class:`~.echo.MulticastEchoFilter` knows its copies by their bytes and takes each back
after the send: two system calls and a comparison per frame, every frame.

Here the frames go out on a socket of their own instead (:func:`own_sender`), connected to
the group, so that they carry that socket's address and port as their source; and the bus's
receiving socket is given a classic BPF socket filter that drops exactly the datagrams
with that source. Another host's datagrams have another address, and another program on
this machine another port (ours is bound without ``SO_REUSEADDR``, so it is ours alone);
python-can's own members send from the group's port. Nothing else changes: the destination,
the TTL, the loopback (on, as python-can leaves it) and the bytes are python-can's.

The source is the one ``getsockname`` gives after ``connect``: the kernel fixed it there,
and every datagram of that socket carries it. Where routing gives no address
(``0.0.0.0``: a multicast route with no usable source, a host whose address has not come
yet) there is nothing fixed to match — the kernel would choose anew at each send, and a
source of ``0.0.0.0`` is also what another host without an address sends — so
:func:`own_sender` gives None. The benchmarks' namespace gives its route ``src
127.0.0.1`` (:mod:`.netns`). If that address goes away during the run, the socket can send
no more; the echo filter then gives it up (:meth:`~.echo.MulticastEchoFilter.send`).

Linux and IPv4 only; elsewhere, or where the kernel refuses the filter, :func:`own_sender`
gives None and the echo filter knows its copies by their bytes.
"""

from __future__ import annotations

import array
import socket
import struct
import sys

from can.interfaces.udp_multicast.bus import GeneralPurposeUdpMulticastBus

SO_ATTACH_FILTER = 26  # Linux's values; the socket module does not name them
SO_DETACH_FILTER = 27
_SKF_NET_OFF = -0x100000  # classic BPF: an offset from the network (IP) header
_IP_SOURCE = 12  # the IPv4 header's source address
# classic BPF opcodes (linux/filter.h)
_LDH_ABS = 0x28  # A = the 16-bit word at k (k = 0: the UDP header's source port)
_LD_ABS = 0x20  # A = the 32-bit word at k
_JEQ = 0x15  # if A == k: skip jt, else skip jf
_RET = 0x06  # accept k bytes (0: drop)
_ALL = 0xFFFFFFFF


def source_filter(address: str, port: int) -> bytes:
    """A ``struct sock_filter`` program dropping UDP/IPv4 datagrams from ``address:port``.
    A UDP socket's filter sees the UDP header at offset 0."""
    source = struct.unpack("!I", socket.inet_aton(address))[0]
    program = [
        (_LDH_ABS, 0, 0, 0),
        (_JEQ, 0, 3, port),  # another port: accept
        (_LD_ABS, 0, 0, (_SKF_NET_OFF + _IP_SOURCE) & _ALL),
        (_JEQ, 0, 1, source),  # another address: accept
        (_RET, 0, 0, 0),  # ours: dropped
        (_RET, 0, 0, _ALL),
    ]
    return b"".join(struct.pack("HBBI", *instruction) for instruction in program)


def attach(sock: socket.socket, program: bytes) -> None:
    """``program`` as ``sock``'s filter (the kernel copies it: nothing to keep alive)."""
    code = array.array("B", program)
    address, _ = code.buffer_info()
    fprog = struct.pack("HL", len(program) // 8, address)  # struct sock_fprog, native
    sock.setsockopt(socket.SOL_SOCKET, SO_ATTACH_FILTER, fprog)


def detach(sock: socket.socket) -> None:
    """``sock`` without its filter."""
    sock.setsockopt(socket.SOL_SOCKET, SO_DETACH_FILTER, 0)


def own_sender(udp: GeneralPurposeUdpMulticastBus) -> socket.socket | None:
    """A socket to send ``udp``'s datagrams on, whose copies ``udp``'s socket never
    receives; None where that cannot be had."""
    receiving = udp._socket
    if not sys.platform.startswith("linux") or receiving.family != socket.AF_INET:
        return None
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sender.setsockopt(
            socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, struct.pack("@I", udp.hop_limit)
        )
        sender.connect((udp.group, udp.port))
        address, port = sender.getsockname()
        if address == "0.0.0.0":  # no source of our own to know our datagrams by
            sender.close()
            return None
        attach(receiving, source_filter(address, port))
    except OSError:
        sender.close()
        return None
    return sender
