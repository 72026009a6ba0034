"""Building blocks of the flow networks (docs/method.md, "Network").

All convolutions are 3x3 with "same" padding unless stated. Every recurrent layer takes its
previous hidden state as a tensor or ``None``; ``None`` and an all-zeros tensor mean the same
thing, a fresh sequence ("zero state at sequence start"), which is what lets the policy wrapper
reset single batch elements by zeroing their state.

On channels-last CPU tensors (the networks' layout on CPU, see ``agents/flownet.py``) the gate
arithmetic of :class:`ConvGRU` (eq. 4) and of :class:`STConvGRU`'s output (eq. 6) runs in the
compiled kernels of ``agents/_kernels.py`` (autograd Functions below); on anything else in the
torch expressions, which are the reference the tests hold the kernels to.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from losses.kernel_switch import use_cpu_kernels

from . import _kernels  # compiled CPU kernels; set to None (tests do) for the torch reference path

_CHANNELS_LAST = torch.channels_last


def conv3x3(in_channels: int, out_channels: int, stride: int = 1, bias: bool = True) -> nn.Conv2d:
    return nn.Conv2d(in_channels, out_channels, 3, stride=stride, padding=1, bias=bias)


def is_channels_last(tensor: Tensor) -> bool:
    """Whether a 4-D tensor is stored channels-last (and not also NCHW-contiguous)."""
    return not tensor.is_contiguous() and tensor.is_contiguous(memory_format=_CHANNELS_LAST)


def _has_rows(tensor: Tensor) -> bool:
    """Whether (B, C, h, w) ``tensor`` is stored channels-last without gaps, i.e. its memory is
    a C-contiguous (B * h * w, C) matrix of pixel rows."""
    return tensor.permute(0, 2, 3, 1).is_contiguous()


def _pixel_rows(tensor: Tensor):
    """The (B * h * w, C) numpy view of a tensor that :func:`_has_rows`."""
    return tensor.detach().permute(0, 2, 3, 1).numpy().reshape(-1, tensor.shape[1])


def _with_rows(tensor: Tensor) -> Tensor:
    """``tensor`` itself when it :func:`_has_rows`, else a channels-last copy."""
    return tensor if _has_rows(tensor) else tensor.contiguous(memory_format=_CHANNELS_LAST)


def _new_channels_last(like: Tensor, channels: int) -> Tensor:
    return torch.empty(
        (like.shape[0], channels, *like.shape[2:]), dtype=like.dtype, memory_format=_CHANNELS_LAST
    )


def use_gate_kernels(tensor: Tensor) -> bool:
    """Whether the gate arithmetic on ``tensor`` (a convolution's output) runs in the compiled
    kernels: CPU, float32/float64, channels-last layout (what the networks use on CPU), and the
    kernels not switched off (``losses.cpu_kernels``). Anything else takes the torch expressions,
    which are the reference and what CUDA runs."""
    return _kernels is not None and use_cpu_kernels(tensor) and tensor.dim() == 4 and is_channels_last(tensor)


class _GRUUpdates(torch.autograd.Function):
    """ConvGRU updates (eq. 4) of G GRUs of hidden size n whose input-side convolutions sit in
    one tensor (``x_proj``: (B, C, h, w), GRU g's [r, z, candidate] at channels ``offsets[g]`` ..
    ``offsets[g] + 3n``; channels no GRU reads get a zero gradient), each given its hidden-side
    convolution and hidden state (both None = a fresh sequence), in one compiled pass per GRU
    (see ``agents/_kernels.py``). Returns the G new hidden states."""

    @staticmethod
    def forward(ctx, n, offsets, x_proj, *memories):  # type: ignore[override]
        # memories: h_proj_1, hidden_1, ..., h_proj_G, hidden_G
        x_proj = _with_rows(x_proj)
        pairs = [
            (None, None) if hidden is None else (_with_rows(h_proj), _with_rows(hidden))
            for h_proj, hidden in zip(memories[0::2], memories[1::2])
        ]
        forward, _, forward_fresh, _ = _kernels.gru_kernels(_kernels.use_threads(), n)
        x_rows = _pixel_rows(x_proj)
        outs = []
        for offset, (h_proj, hidden) in zip(offsets, pairs):
            out = _new_channels_last(x_proj, n)
            if hidden is None:
                forward_fresh(x_rows, offset, _pixel_rows(out))
            else:
                forward(x_rows, offset, _pixel_rows(h_proj), _pixel_rows(hidden), _pixel_rows(out))
            outs.append(out)
        ctx.n, ctx.offsets = n, tuple(offsets)
        ctx.fresh = [hidden is None for _, hidden in pairs]
        ctx.save_for_backward(x_proj, *(t for pair in pairs if pair[1] is not None for t in pair))
        return tuple(outs)

    @staticmethod
    def backward(ctx, *grad_outs):  # type: ignore[override]
        x_proj, *saved = ctx.saved_tensors
        n = ctx.n
        _, backward, _, backward_fresh = _kernels.gru_kernels(_kernels.use_threads(), n)
        # Each GRU writes its own 3n columns of grad_x; zeros first only if some are left over.
        covered = sorted(ctx.offsets) == list(range(0, x_proj.shape[1], 3 * n))
        grad_x = _new_channels_last(x_proj, x_proj.shape[1])
        if not covered:
            grad_x.zero_()
        x_rows, gx_rows = _pixel_rows(x_proj), _pixel_rows(grad_x)
        grads = [None, None, grad_x]
        for offset, fresh, grad_out in zip(ctx.offsets, ctx.fresh, grad_outs):
            grad_out = _with_rows(torch.zeros_like(x_proj[:, :n]) if grad_out is None else grad_out)
            if fresh:
                backward_fresh(x_rows, offset, _pixel_rows(grad_out), gx_rows)
                grads += [None, None]
                continue
            h_proj, hidden = saved.pop(0), saved.pop(0)
            grad_h = _new_channels_last(h_proj, h_proj.shape[1])
            grad_hidden = _new_channels_last(hidden, hidden.shape[1])
            backward(
                x_rows, offset, _pixel_rows(h_proj), _pixel_rows(hidden), _pixel_rows(grad_out),
                gx_rows, _pixel_rows(grad_h), _pixel_rows(grad_hidden),
            )
            grads += [grad_h, grad_hidden]
        return tuple(grads)


def gru_updates(convgrus, x_proj: Tensor, hidden_states, offsets=None) -> list[Tensor]:
    """The compiled eq. 4 of several :class:`ConvGRU` of one hidden size sharing one input-side
    tensor ``x_proj`` (their ``x_convs`` outputs at channel ``offsets``, by default side by side
    from 0); ``hidden_states``: one previous state (or None) each. Only for tensors that pass
    :func:`use_gate_kernels`."""
    n = convgrus[0].hidden_size
    if offsets is None:
        offsets = [3 * n * g for g in range(len(convgrus))]
    memories = []
    for gru, hidden in zip(convgrus, hidden_states):
        memories += [None, None] if hidden is None else [gru.h_convs(hidden), hidden]
    return list(_GRUUpdates.apply(n, tuple(offsets), x_proj, *memories))


class _OutputGate(torch.autograd.Function):
    """``sig(gate_x + gate_h) . tanh(fusion)`` (eq. 6) in one compiled pass."""

    @staticmethod
    def forward(ctx, gate_x, gate_h, fusion):  # type: ignore[override]
        gate_x, gate_h, fusion = (_with_rows(t) for t in (gate_x, gate_h, fusion))
        out = _new_channels_last(fusion, fusion.shape[1])
        _kernels.output_gate_kernels(_kernels.use_threads())[0](
            _pixel_rows(gate_x), _pixel_rows(gate_h), _pixel_rows(fusion), _pixel_rows(out)
        )
        ctx.save_for_backward(gate_x, gate_h, fusion)
        return out

    @staticmethod
    def backward(ctx, grad_out):  # type: ignore[override]
        gate_x, gate_h, fusion = ctx.saved_tensors
        grad_out = _with_rows(grad_out)
        grad_gate = _new_channels_last(fusion, fusion.shape[1])
        grad_fusion = _new_channels_last(fusion, fusion.shape[1])
        _kernels.output_gate_kernels(_kernels.use_threads())[1](
            _pixel_rows(gate_x), _pixel_rows(gate_h), _pixel_rows(fusion), _pixel_rows(grad_out),
            _pixel_rows(grad_gate), _pixel_rows(grad_fusion),
        )
        return grad_gate, grad_gate, grad_fusion


def output_gate(gate_x: Tensor, gate_h: Tensor, fusion: Tensor) -> Tensor:
    """ST-ConvGRU output (eq. 6): ``o . tanh(fusion)`` with ``o = sig(gate_x + gate_h)``; all
    (B, C, h, w). Compiled on channels-last CPU tensors, torch expressions otherwise."""
    if use_gate_kernels(fusion):
        return _OutputGate.apply(gate_x, gate_h, fusion)
    return torch.sigmoid(gate_x + gate_h) * torch.tanh(fusion)


def _planes(tensor: Tensor):
    """The (B, C, h * w) numpy view of an NCHW-contiguous (B, C, h, w) tensor."""
    return tensor.detach().numpy().reshape(tensor.shape[0], tensor.shape[1], -1)


def _image_rows(tensor: Tensor):
    """The (B, h * w, C) numpy view of a (B, C, h, w) tensor that :func:`_has_rows`."""
    return tensor.detach().permute(0, 2, 3, 1).numpy().reshape(tensor.shape[0], -1, tensor.shape[1])


class _PackRefinerInput(torch.autograd.Function):
    """``[tanh(a), hidden]``: the flow refiner's input and hidden state as one NCHW tensor
    (``a``: the channels-last head output; ``hidden``: NCHW)."""

    @staticmethod
    def forward(ctx, head, hidden):  # type: ignore[override]
        head, hidden = _with_rows(head), hidden.contiguous()
        n = head.shape[1]
        packed = head.new_empty((head.shape[0], 2 * n, *head.shape[2:]))
        _kernels.refiner_kernels(_kernels.use_threads(), n)[0](
            _image_rows(head), _planes(hidden), _planes(packed)
        )
        ctx.save_for_backward(packed)
        return packed

    @staticmethod
    def backward(ctx, grad_packed):  # type: ignore[override]
        (packed,) = ctx.saved_tensors
        n = packed.shape[1] // 2
        grad_packed = grad_packed.contiguous()
        grad_head = _new_channels_last(packed, n)
        _kernels.refiner_kernels(_kernels.use_threads(), n)[1](
            _planes(packed), _planes(grad_packed), _image_rows(grad_head)
        )
        return grad_head, grad_packed[:, n:]


class _RefinerUpdate(torch.autograd.Function):
    """Eq. 4 from the merged convolution ``q`` = [r, z, Wxh*X, Whh*H] (pre-activations) and the
    hidden state, all NCHW (see ``agents/_kernels.py``, ``_make_refiner``)."""

    @staticmethod
    def forward(ctx, q, hidden):  # type: ignore[override]
        q, hidden = q.contiguous(), hidden.contiguous()
        out = torch.empty_like(hidden)
        _kernels.refiner_kernels(_kernels.use_threads(), hidden.shape[1])[2](
            _planes(q), _planes(hidden), _planes(out)
        )
        ctx.save_for_backward(q, hidden)
        return out

    @staticmethod
    def backward(ctx, grad_out):  # type: ignore[override]
        q, hidden = ctx.saved_tensors
        grad_out = grad_out.contiguous()
        grad_q, grad_hidden = torch.empty_like(q), torch.empty_like(hidden)
        _kernels.refiner_kernels(_kernels.use_threads(), hidden.shape[1])[3](
            _planes(q), _planes(hidden), _planes(grad_out), _planes(grad_q), _planes(grad_hidden)
        )
        return grad_q, grad_hidden


def _merged_refiner_conv(gru: "ConvGRU") -> tuple[Tensor, Tensor]:
    """The weight and bias of one convolution of ``[X, H]`` giving [Wxr*X + Whr*H + b_r,
    Wxz*X + Whz*H + b_z, Wxh*X + b_h, Whh*H] from ``gru``'s two convolutions (differentiable:
    the gradients reach ``x_convs`` and ``h_convs``)."""
    n = gru.hidden_size
    wx, wh = gru.x_convs.weight, gru.h_convs.weight  # (3n, C_in, k, k), (3n, n, k, k)
    gates = torch.cat([wx[: 2 * n], wh[: 2 * n]], dim=1)
    candidate_x = torch.cat([wx[2 * n :], wh.new_zeros(n, n, *wh.shape[2:])], dim=1)
    candidate_h = torch.cat([wx.new_zeros(n, wx.shape[1], *wx.shape[2:]), wh[2 * n :]], dim=1)
    bias = torch.cat([gru.x_convs.bias, gru.x_convs.bias.new_zeros(n)])
    return torch.cat([gates, candidate_x, candidate_h]), bias


def refine_flow(gru: "ConvGRU", head: Tensor, prior: Tensor | None) -> Tensor:
    """FGD-Net's refinement of one scale's estimate (eqs. 10-11): ``u = gru(tanh(head), prior)``.

    head: (B, n, h, w) the flow head's convolution output (before the tanh); prior: (B, n, h, w)
    the aligned, downsampled prior flow ``ubar`` in network units, or None (fresh sequence).
    Returns u (B, n, h, w). On a channels-last CPU head (the networks on CPU) the work is
    :func:`_merged_refiner_conv`'s one convolution between two compiled passes, in NCHW, and u
    is NCHW. Otherwise it is ``gru`` itself, in ``head``'s layout."""
    n = gru.hidden_size
    if not use_gate_kernels(head) or gru.x_convs.in_channels != n:
        if prior is not None and is_channels_last(head):
            prior = prior.contiguous(memory_format=_CHANNELS_LAST)
        return gru(torch.tanh(head), prior)
    if prior is None:  # the same arithmetic as for a zeroed prior, so that the two agree bitwise
        prior = head.new_zeros(head.shape)
    weight, bias = _merged_refiner_conv(gru)
    packed = _PackRefinerInput.apply(head, prior)
    q = F.conv2d(packed, weight, bias, padding=gru.x_convs.padding)
    return _RefinerUpdate.apply(q, prior)


class ConvDown(nn.Module):
    """``conv_down(x) = relu(conv2d_stride2(x))``: halves the resolution."""

    def __init__(self, in_channels: int, out_channels: int):
        super().__init__()
        self.conv = conv3x3(in_channels, out_channels, stride=2)

    def forward(self, x: Tensor) -> Tensor:
        return F.relu(self.conv(x))


class ConvUp(nn.Module):
    """``conv_up(x) = relu(conv2d(upsample_bilinear(x)))``, x2 or to a given ``size``."""

    def __init__(self, in_channels: int, out_channels: int):
        super().__init__()
        self.conv = conv3x3(in_channels, out_channels)

    def forward(self, x: Tensor, size: tuple[int, int] | None = None) -> Tensor:
        if size is None:
            size = (2 * x.shape[-2], 2 * x.shape[-1])
        x = F.interpolate(x, size=size, mode="bilinear", align_corners=False)
        return F.relu(self.conv(x))


class ResidualBlock(nn.Module):
    """``RB(x) = relu(conv(relu(conv(x))) + x)`` (FERE-Net residual module, eq. 8)."""

    def __init__(self, channels: int):
        super().__init__()
        self.conv1 = conv3x3(channels, channels)
        self.conv2 = conv3x3(channels, channels)

    def forward(self, x: Tensor) -> Tensor:
        return F.relu(self.conv2(F.relu(self.conv1(x))) + x)


class ConvGRU(nn.Module):
    """Convolutional GRU, paper eq. 4.

    ``r = sig(Wxr*X + Whr*H)``, ``z = sig(Wxz*X + Whz*H)``,
    ``Hhat = tanh(r . (Whh*H) + Wxh*X)``, ``H' = (1 - z) . H + z . Hhat``.

    The three input-side convolutions are one conv with 3*hidden outputs (``x_convs``), the three
    hidden-side ones another (``h_convs``, no bias: the biases sit on the input side, so that
    ``r`` gates exactly ``Whh*H`` as eq. 4 writes it).

    Args:
        x: (B, C_in, h, w) input.
        hidden: (B, C_hidden, h, w) previous hidden state, or None for a fresh sequence (zeros).
    Returns:
        (B, C_hidden, h, w) new hidden state.
    """

    def __init__(self, input_size: int, hidden_size: int, kernel_size: int = 3):
        super().__init__()
        self.hidden_size = hidden_size
        padding = kernel_size // 2
        self.x_convs = nn.Conv2d(input_size, 3 * hidden_size, kernel_size, padding=padding)
        self.h_convs = nn.Conv2d(hidden_size, 3 * hidden_size, kernel_size, padding=padding, bias=False)

    def forward(self, x: Tensor, hidden: Tensor | None) -> Tensor:
        return self.step(self.x_convs(x), hidden)

    def step(self, x_proj: Tensor, hidden: Tensor | None) -> Tensor:
        """The update given the input side already convolved: ``x_proj = x_convs(x)``,
        (B, 3 * C_hidden, h, w) = [Wxr*X, Wxz*X, Wxh*X]."""
        n = self.hidden_size
        if use_gate_kernels(x_proj):
            return gru_updates([self], x_proj, [hidden])[0]  # eq. 4, compiled
        if hidden is None:
            # Zero state: Whh*0 = 0 (no hidden-side bias), so skip the conv but run the same
            # arithmetic as for a zeroed state: results are bitwise identical.
            hidden = x_proj.new_zeros(x_proj.shape[0], n, *x_proj.shape[2:])
            h_proj = torch.zeros_like(x_proj)
        else:
            h_proj = self.h_convs(hidden)
        gates = torch.sigmoid(x_proj[:, : 2 * n] + h_proj[:, : 2 * n])  # eq. 4, r and z
        r, z = gates[:, :n], gates[:, n:]
        candidate = torch.tanh(torch.addcmul(x_proj[:, 2 * n :], r, h_proj[:, 2 * n :]))  # eq. 4, Hhat
        return torch.addcmul(hidden, z, candidate - hidden)  # eq. 4, (1 - z) . H + z . Hhat


class STConvGRU(nn.Module):
    """Spatio-temporal ConvGRU of FERE-Net's first module (paper eqs. 5-6).

    Two memories: its own ``S`` (carried between windows) and ``M``, the deepest encoder's
    previous hidden state brought up to this module's resolution (built by the caller).

    ``S_k = ConvGRU_a(X, S_{k-1})``; ``Mbar_k = ConvGRU_b(X, M_{k-1})``;
    ``o_k = sig(Wfo*X + Wso*S_k + Wmo*Mbar_k)``; ``F_k = o_k . tanh(W_1x1 * [Mbar_k, S_k])``.

    Args:
        x: (B, C, h, w) input ``X``.
        own_memory: (B, C, h, w) ``S_{k-1}`` or None (fresh).
        deep_memory: (B, C, h, w) ``M_{k-1}`` or None (fresh).
    Returns:
        (output ``F_k``, new own memory ``S_k``), both (B, C, h, w).
    """

    def __init__(self, channels: int):
        super().__init__()
        self.gru_own = ConvGRU(channels, channels)  # ConvGRU_a, eq. 5
        self.gru_deep = ConvGRU(channels, channels)  # ConvGRU_b, eq. 5 (the M path)
        # o_k (eq. 6): Wfo*X (with the bias) + [Wmo, Wso] * [Mbar_k, S_k].
        self.gate_input = conv3x3(channels, channels)
        self.gate_hidden = conv3x3(2 * channels, channels, bias=False)
        # Wmm, Wss fused as one 1x1 conv over [Mbar_k, S_k] (eq. 6).
        self.fusion = nn.Conv2d(2 * channels, channels, 1)

    def forward(
        self, x: Tensor, own_memory: Tensor | None, deep_memory: Tensor | None
    ) -> tuple[Tensor, Tensor]:
        # Both GRUs' input sides in one call (same X, one pass); Wfo*X apart: with oneDNN on
        # CPU, 6 x hidden output channels in one conv run faster than 7 (at CPU width, 16 -> 96
        # plus 16 -> 16 took ~14 ms against ~20 ms for 16 -> 112, 128x128 batch 8, one thread).
        input_convs = [self.gru_own.x_convs, self.gru_deep.x_convs]
        weight = torch.cat([conv.weight for conv in input_convs])
        bias = torch.cat([conv.bias for conv in input_convs])
        projections = F.conv2d(x, weight, bias, padding=1)
        if use_gate_kernels(projections):  # eq. 5, S_k and Mbar_k, compiled
            own, deep = gru_updates([self.gru_own, self.gru_deep], projections, [own_memory, deep_memory])
        else:
            n = 3 * self.gru_own.hidden_size
            own = self.gru_own.step(projections[:, :n], own_memory)  # eq. 5, S_k
            deep = self.gru_deep.step(projections[:, n : 2 * n], deep_memory)  # eq. 5, Mbar_k
        memories = torch.cat([deep, own], dim=1)
        # eq. 6: o_k = sig(Wfo*X + [Wmo, Wso]*[Mbar_k, S_k]), F_k = o_k . tanh(W_1x1*[Mbar_k, S_k])
        out = output_gate(self.gate_input(x), self.gate_hidden(memories), self.fusion(memories))
        return out, own


# -- layers of the published baselines (docs/method.md, "Baselines") ---------------------------


class HagenaarsConvGRU(nn.Module):
    """The ConvGRU of Hagenaars et al.'s ConvGRU-EV-FlowNet (a variant of eq. 4).

    With ``[a, b]`` the channel concatenation and ``*`` a 3x3 convolution with bias:
    ``z = sig(Wz * [X, H] + bz)``, ``r = sig(Wr * [X, H] + br)``,
    ``Hhat = tanh(Wh * [X, r . H] + bh)``, ``H' = (1 - z) . H + z . Hhat``.
    Unlike eq. 4 (which gates the convolved state, ``r . (Whh*H)``), the reset gate scales the
    hidden state before its convolution. Weights orthogonal (each gate's kernel as one
    (hidden, (C_in + hidden) k^2) matrix), biases 0, as in the authors' description.
    Its interface (arguments, docstring, first lines of ``__init__``) is :class:`ConvGRU`'s, so
    that the networks take either; the gates differ.

    Args:
        x: (B, C_in, h, w) input.
        hidden: (B, C_hidden, h, w) previous hidden state, or None for a fresh sequence (zeros).
    Returns:
        (B, C_hidden, h, w) new hidden state.
    """

    def __init__(self, input_size: int, hidden_size: int, kernel_size: int = 3):
        super().__init__()
        self.hidden_size = hidden_size
        padding = kernel_size // 2
        both = input_size + hidden_size
        self.update_gate = nn.Conv2d(both, hidden_size, kernel_size, padding=padding)
        self.reset_gate = nn.Conv2d(both, hidden_size, kernel_size, padding=padding)
        self.candidate = nn.Conv2d(both, hidden_size, kernel_size, padding=padding)
        for conv in (self.update_gate, self.reset_gate, self.candidate):
            nn.init.orthogonal_(conv.weight)
            nn.init.zeros_(conv.bias)

    def forward(self, x: Tensor, hidden: Tensor | None) -> Tensor:
        if hidden is None:
            hidden = x.new_zeros(x.shape[0], self.hidden_size, *x.shape[2:])
        both = torch.cat([x, hidden], dim=1)
        z = torch.sigmoid(self.update_gate(both))
        r = torch.sigmoid(self.reset_gate(both))
        candidate = torch.tanh(self.candidate(torch.cat([x, r * hidden], dim=1)))
        return (1 - z) * hidden + z * candidate


def zhu_init_(conv: nn.Conv2d, factor: float = 0.1) -> nn.Conv2d:
    """EV-FlowNet's initialisation (Zhu et al.'s code: TensorFlow's variance scaling with factor
    0.1 over the fan-in): weights from a normal truncated at two standard deviations,
    std = sqrt(1.3 factor / fan_in) (1.3 corrects for the truncation), biases 0."""
    fan_in = conv.weight.shape[1] * conv.weight.shape[2] * conv.weight.shape[3]
    std = (1.3 * factor / fan_in) ** 0.5
    nn.init.trunc_normal_(conv.weight, 0.0, std, -2 * std, 2 * std)
    if conv.bias is not None:
        nn.init.zeros_(conv.bias)
    return conv


class ZhuResidualBlock(nn.Module):
    """EV-FlowNet's residual block: ``RB(x) = x + relu(conv(relu(conv(x))))`` (both convs 3x3
    with ReLU, no activation after the sum; EV-MGRFlowNet's :class:`ResidualBlock` instead
    applies the ReLU after the sum)."""

    def __init__(self, channels: int):
        super().__init__()
        self.conv1 = zhu_init_(conv3x3(channels, channels))
        self.conv2 = zhu_init_(conv3x3(channels, channels))

    def forward(self, x: Tensor) -> Tensor:
        return x + F.relu(self.conv2(F.relu(self.conv1(x))))


class ConvUpNearestReflect(nn.Module):
    """EV-FlowNet's upsampling convolution: nearest-neighbour x2, reflection padding of 1, 3x3
    convolution without padding, ReLU. ``forward(x)``: (B, C_in, h, w) -> (B, C_out, 2h, 2w)."""

    def __init__(self, in_channels: int, out_channels: int):
        super().__init__()
        self.conv = zhu_init_(nn.Conv2d(in_channels, out_channels, 3))

    def forward(self, x: Tensor) -> Tensor:
        x = F.interpolate(x, scale_factor=2, mode="nearest")
        return F.relu(self.conv(F.pad(x, (1, 1, 1, 1), mode="reflect")))
