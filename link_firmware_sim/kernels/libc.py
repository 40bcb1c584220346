"""The C library's ``poll``, ``recv`` and ``send`` as numba intrinsics, for the lockstep loop.

Linked by symbol name, so that numba caches the kernels that call them like any other. Without the
compiled kernels they raise: the loop never runs then.
"""

from __future__ import annotations

from companion.kernels.jit import ENABLED

__all__ = ["POLLIN", "MSG_NOSIGNAL", "c_poll", "c_recv", "c_send"]

POLLIN = 0x1
MSG_NOSIGNAL = 0x4000  # Linux's (the same-host link is Linux's: SOCK_SEQPACKET, SO_PEERCRED)

if ENABLED:
    from llvmlite import ir as _ir
    from numba import types as _types
    from numba.core import cgutils as _cgutils
    from numba.extending import intrinsic as _intrinsic

    _I32, _I64, _P8 = _ir.IntType(32), _ir.IntType(64), _ir.IntType(8).as_pointer()

    def _data_ptr(context, builder, array_type, value):
        return builder.bitcast(context.make_array(array_type)(context, builder, value).data, _P8)

    def _libc_call(builder, name, ret, params, args):
        """A call of the C library's ``name`` by symbol (numba caches code that links libc by name)."""
        fn = _cgutils.get_or_insert_function(builder.module, _ir.FunctionType(ret, params), name)
        return builder.call(fn, args)

    @_intrinsic
    def c_poll(typingctx, fds, nfds, timeout_ms):
        """``poll(2)`` on ``fds``: int32 pairs ``(fd, events | revents << 16)``, a ``struct pollfd`` each."""
        def codegen(context, builder, sig, args):
            return _libc_call(builder, "poll", _I32, [_P8, _I64, _I32],
                              [_data_ptr(context, builder, sig.args[0], args[0]), args[1], args[2]])
        return _types.int32(fds, _types.int64, _types.int32), codegen

    def _transfer(name: str):
        """The C library's ``name`` (``recv`` or ``send``: ``(fd, buf, n, flags)``, the first ``n``
        bytes of ``buf``, uint8) as an intrinsic."""
        def call(typingctx, fd, buf, n, flags):
            def codegen(context, builder, sig, args):
                return _libc_call(builder, name, _I64, [_I32, _P8, _I64, _I32],
                                  [args[0], _data_ptr(context, builder, sig.args[1], args[1]), args[2], args[3]])
            return _types.int64(_types.int32, buf, _types.int64, _types.int32), codegen
        call.__name__ = call.__qualname__ = f"_c_{name}"
        return _intrinsic(call)

    c_recv, c_send = _transfer("recv"), _transfer("send")
else:  # the numpy path never runs the loop (the firmware's lockstep loop is off without the kernels)
    def c_poll(fds, nfds, timeout_ms):
        raise RuntimeError("the lockstep loop needs the compiled kernels")

    c_recv = c_send = c_poll
