"""Temporal fusion: the paper's equation (11) for sparse memories, and the dense baseline.

Sparse (SUIT): every stored cell feature f is moved by the ego transform to its position x in
the current frame, then for every displacement bin k (velocity v_k, time gap dt) it is added at
the current-grid cell containing ``x + v_k * dt`` with weight ``p(R_{t-1} | I_{t-1}) * q_k``
(p: the cell's heatmap probability; q: GeoNet's distribution). Nearest-cell splatting is used
(bins are finer than a cell; features live at cell resolution). Variants: ``sparse`` uses a
single zero displacement, ``sparse_velocity`` the predicted velocity times dt.

The warped map F^_t is concatenated with F_t and fused by a 1x1 conv. Because the conv is
linear, its half that acts on F^_t is applied to the few memory features *before* they are
scattered (``W2 sum_i w_i f_i == sum_i w_i W2 f_i``): the result equals concat + 1x1 conv on
the dense maps at a fraction of the cost. The projected term stays sparse (:class:`PastTerm`:
the rows it touches) and is added into the fused map in place, so no dense past map is built
when the map is channels-last (the inference copy's layout). ``fusion_gate: carry_branch``
has two such terms (:class:`BranchTerms`). W1 starts as the identity and W2
at zero, so a fine-tuned SUIT model starts exactly as the single-frame model it was
initialised from.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
import typing

import numpy as np
from numpy.typing import NDArray
import torch
from torch import Tensor, nn
import torch.nn.functional as F

from suit_ros.model.grid import BEVGrid
from suit_ros.model.inference import compiled_ok


@dataclass
class PastTerm:
    """A sparse past term: ``values (R, C)`` to add at the flat cells ``index (R,)``
    (``(b * H + row) * W + col``, repeats allowed) of a ``shape = (B, C, H, W)`` map."""

    index: Tensor
    values: Tensor
    shape: tuple[int, int, int, int]
    # the index sorted, without repeats (one row per cell, as the sparse past terms give it;
    # :meth:`at` trusts it: whoever changes the index in place must clear it)
    distinct: bool = False

    def rows(self) -> Tensor:
        """The term summed per cell, as the ``(B * H * W, C)`` rows of the map."""
        B, C, H, W = self.shape
        out = self.values.new_zeros(B * H * W, C)
        out.index_add_(0, self.index, self.values)
        return out

    def at(self, flat: Tensor) -> Tensor:
        """The term summed per cell at the flat cells ``flat`` ``(N,)``: ``(N, C)`` rows (zero
        where it adds nothing), without forming the map's rows."""
        if self.distinct:
            cells, summed = self.index, self.values
        else:
            cells, where = torch.unique(self.index, return_inverse=True)
            summed = self.values.new_zeros(len(cells), self.values.shape[1])
            summed.index_add_(0, where, self.values)
        out = self.values.new_zeros(len(flat), self.values.shape[1])
        if len(cells):
            at = torch.searchsorted(cells, flat).clamp(max=len(cells) - 1)
            hit = cells[at] == flat
            out[hit] = summed[at[hit]]
        return out

    def dense(self) -> Tensor:
        """The term as a ``(B, C, H, W)`` map (channels-last memory)."""
        B, C, H, W = self.shape
        return self.rows().view(B, H, W, C).permute(0, 3, 1, 2)

    def add_to(self, x: Tensor) -> Tensor:
        """``x += term`` in place (in ``x``'s dtype); only the touched rows when ``x`` is
        channels-last, a dense add otherwise. Returns ``x``."""
        B, C, H, W = x.shape
        if (B, C, H, W) != self.shape:
            raise ValueError(f'past term of shape {self.shape} added to a map of {tuple(x.shape)}')
        if x.is_contiguous(memory_format=torch.channels_last):
            x.permute(0, 2, 3, 1).view(B * H * W, C).index_add_(0, self.index,
                                                                 self.values.to(x.dtype))
            return x
        return x.add_(self.dense().to(x.dtype))


class TemporalFusion(nn.Module):
    """``fused = W1 F_t + W2 F^_t + b``, i.e. a 1x1 conv over ``concat(F_t, F^_t)``."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.current = nn.Conv2d(channels, channels, 1)
        self.past = nn.Linear(channels, channels, bias=False)
        with torch.no_grad():
            self.current.weight.copy_(torch.eye(channels)[:, :, None, None])
            assert self.current.bias is not None
            self.current.bias.zero_()
            self.past.weight.zero_()
        # set by an inference copy whose W1 is still the identity (a model whose fusion was
        # never trained, as a carry branch on the single-frame model): W1 F_t is F_t itself,
        # exactly (products by 1 and 0, sums with 0), so the conv is skipped for a copy
        self.identity_current = False
        # likewise, set when W2 is zero: the past term adds nothing and is not computed
        self.zero_past = False

    def mark_identity(self) -> bool:
        """Set :attr:`identity_current` when W1 is the identity and its bias zero, and
        :attr:`zero_past` when W2 is zero (inference copies only: trained weights move);
        :return: whether W1 is the identity."""
        conv = unwrap_conv(self.current)                # an inference copy's dtype wrapper
        w = conv.weight.detach().float()[:, :, 0, 0]
        bias = conv.bias
        self.identity_current = bool(
            w.shape[0] == w.shape[1] and torch.equal(w, torch.eye(w.shape[0], device=w.device))
            and (bias is None or not bias.detach().any()))
        self.zero_past = not bool(self.past.weight.detach().any())
        return self.identity_current

    def current_weights(self, dtype: torch.dtype) -> tuple[Tensor, Tensor | None]:
        """W1 ``(C, C_in)`` and its bias in ``dtype``, for products over a few rows; kept
        where :func:`~suit_ros.model.inference.keep_gathered_weights` set ``gathered_cache``
        (an inference copy)."""
        def build() -> tuple[Tensor, Tensor | None]:
            conv = unwrap_conv(self.current)
            return (conv.weight[:, :, 0, 0].to(dtype),
                    None if conv.bias is None else conv.bias.to(dtype))
        return kept(self, self.current, dtype, build)

    def _current(self, current: Tensor) -> Tensor:
        """W1 F_t, as a fresh tensor (the past term is added into it in place)."""
        if self.identity_current:
            dtype = getattr(self.current, 'out_dtype', current.dtype)
            return current.to(dtype, copy=True)
        out: Tensor = self.current(current)
        return out

    def past_dense(self, warped: Tensor) -> Tensor:
        """Apply W2 to a dense ``(B, C, H, W)`` map."""
        return torch.einsum('oc,bchw->bohw', self.past.weight, warped)

    def forward(self, current: Tensor, past_term: Tensor | PastTerm | None) -> Tensor:
        """Fuse ``(B, C, H, W)`` current features with an already W2-projected past term."""
        out = self._current(current)
        # in place: the conv's output is fresh (and autograd does not need it for the conv);
        # in the conv's dtype (bfloat16 in a bfloat16 inference copy)
        return out if past_term is None else _add(out, past_term)

    def forward_branches(self, current: Tensor, own: PastTerm, carry: Tensor | PastTerm
                         ) -> tuple[Tensor, Tensor]:
        """``forward(current, own)`` and ``forward(current, carry)`` with W1 applied once
        (the same values, bit for bit)."""
        out = self._current(current)
        other = _add(out.clone(), carry)
        return own.add_to(out), other


def unwrap_conv(module: nn.Module) -> nn.Conv2d:
    """The convolution inside an inference copy's dtype wrapper (or the module itself)."""
    while not isinstance(module, nn.Conv2d):
        module = typing.cast(nn.Module, module.inner)
    return module


@dataclass
class FoldedFused:
    """The fused map ``W1 F_t + b + past`` of an inference copy whose heads read it through
    their first layer composed with W1 (:class:`~suit_ros.model.head.HeadFold`): the dense map
    is never formed, which saves the 1 x 1 convolution over every cell (a tenth of a float32
    step). The memory's samples read their rows (:meth:`rows`); :meth:`dense` forms the map."""

    current: Tensor                 # F_t, (B, C, H, W)
    past: PastTerm | None           # already W2-projected (and gated, where gated)
    fusion: TemporalFusion

    @property
    def shape(self) -> tuple[int, int, int, int]:
        """The fused map's shape."""
        B, _, H, W = self.current.shape
        return B, self.fusion.past.out_features, H, W

    def dense(self) -> Tensor:
        """The fused map itself (as :meth:`TemporalFusion.forward` gives it)."""
        fused: Tensor = self.fusion(self.current, self.past)
        return fused

    def rows(self, flat: Tensor) -> Tensor:
        """The fused map's rows ``(N, C)`` at flat cells ``(b * H + row) * W + col``, in float32
        (float64 on a float64 map; a low-precision inference copy's dense map rounds them, and
        a few hundred rows gain nothing from its speed)."""
        B, C, H, W = self.current.shape
        exact = gathered_dtype(self.current.dtype)
        weight, bias = self.fusion.current_weights(exact)
        x = self.current.permute(0, 2, 3, 1).reshape(B * H * W, C)[flat].to(exact)
        out = x @ weight.t()
        if bias is not None:
            out = out + bias
        if self.past is not None and len(self.past.index):
            out += self.past.at(flat).to(exact)
        return out


def state_key(module: nn.Module) -> tuple[typing.Any, ...]:
    """Each parameter's and buffer's device, storage and in-place version: what a load, a
    move or an update of a module's weights changes."""
    return tuple((t.device, t.data_ptr(), t._version)
                 for t in (*module.parameters(), *module.buffers()))


def weights_key(module: nn.Module, dtype: torch.dtype) -> tuple[typing.Any, ...]:
    """What a module's weights converted for gathered products depend on: the target dtype,
    inference mode (whose tensors autograd refuses) and :func:`state_key`."""
    return (dtype, torch.is_inference_mode_enabled()) + state_key(module)


Built = typing.TypeVar('Built')


def kept(owner: nn.Module, source: nn.Module, dtype: torch.dtype,
         build: typing.Callable[[], Built]) -> Built:
    """``build()``, kept per ``dtype`` in ``owner``'s ``gathered_cache`` (set on inference
    copies by :func:`~suit_ros.model.inference.keep_gathered_weights`) while ``source``'s
    weights stay as they were (:func:`weights_key`); built every call without a cache."""
    cache: dict[torch.dtype, tuple[typing.Any, typing.Any]] | None = getattr(
        owner, 'gathered_cache', None)
    if cache is None:
        return build()
    key = weights_key(source, dtype)
    if dtype not in cache or cache[dtype][0] != key:
        cache[dtype] = (key, build())
    value: Built = cache[dtype][1]
    return value


def gathered_dtype(dtype: torch.dtype) -> torch.dtype:
    """What a gathered product over a few hundred rows computes in: float32 for a low-precision
    map (bfloat16 saves nothing on so few rows and its conversions cost), else the map's own."""
    return dtype if dtype in (torch.float32, torch.float64) else torch.float32


def _add(out: Tensor, term: Tensor | PastTerm) -> Tensor:
    """``out += term`` in place, in ``out``'s dtype."""
    if isinstance(term, PastTerm):
        return term.add_to(out)
    return out.add_(term.to(out.dtype))


@dataclass
class BranchTerms:
    """The two past terms of ``fusion_gate: carry_branch``: ``own`` (the model's W2 on its own
    samples, added everywhere as without a gate) and ``carry`` (the carry branch's W2 on every
    sample, carried ones included, for the unobserved cells)."""

    own: PastTerm
    carry: PastTerm
    # the carry head's input (the carry term where the input has no returns), once fused
    carry_input: Tensor | FoldedFused | None = None
    # the carry term where the input has no returns, once gated
    carry_gated: Tensor | PastTerm | None = None


def sparse_past_term(features: Tensor, probs: Tensor, mask: Tensor, positions: Tensor,
                     batch_index: Tensor, displacements: Tensor, q: Tensor,
                     projection: nn.Linear, grid: BEVGrid, batch_size: int,
                     prune: float = 0.0) -> PastTerm:
    """Equation (11): the W2-projected past term from a sparse memory, for a ``(B, C, H, W)``
    map (:class:`PastTerm`; ``.dense()`` for the map).

    Every (sample, cell, bin) triple adds ``p * q * W2 f`` at the current-grid cell that
    contains ``position + displacement``; only the cells that receive a weight become the
    term's rows (:func:`sparse_past_terms`).

    :param features: ``(M, P, C)`` memory features; ``probs``/``mask``: ``(M, P)``.
    :param positions: ``(M, P, 2)`` cell positions already moved into the current frame.
    :param displacements: ``(M, K, 2)`` metres per displacement bin (already times dt).
    :param q: ``(M, K)`` probability of each bin (GeoNet softmax; ones for a single bin).
    :param prune: treat bins with ``q < prune`` as zero (inference speed-up, no effect on the
        result beyond those bins' tiny weights).
    """
    return sparse_past_terms(features, probs, mask, positions, batch_index, displacements, q,
                             [(projection, None)], grid, batch_size, prune)[0]


def sparse_past_terms(features: Tensor, probs: Tensor, mask: Tensor, positions: Tensor,
                      batch_index: Tensor, displacements: Tensor, q: Tensor,
                      projections: Sequence[tuple[nn.Linear, Tensor | None]], grid: BEVGrid,
                      batch_size: int, prune: float = 0.0) -> list[PastTerm]:
    """:func:`sparse_past_term` for several projections, each of the samples it names (an
    index into the ``M`` samples, or None for all), with the samples' destinations and weights
    found once (a carry branch's own and carry terms).

    Two ways to the same sums, by cost: with every bin weighted (``prune`` 0: training, or a
    model without GeoNet, whose single bin is the whole displacement) each
    sample's weights are accumulated over a local ``D x D`` window of destinations first and
    multiplied with its ``(P, C)`` projected features (:func:`_window_terms`: ``D^2`` rows a
    sample where the triples are ``P K``); with pruned bins (inference: a few per sample cell)
    only the triples of non-zero weight are formed (:func:`_triple_terms`: no window, no
    host sync for its size; on the CPU without autograd in one compiled pass that sums the
    weighted features per cell before projecting them, :func:`_compiled_triple_terms`). The
    rows differ only in summation order (tested)."""
    M, P, C = features.shape
    H, W = grid.H, grid.W
    shapes = [(batch_size, proj.out_features, H, W) for proj, _ in projections]
    if M == 0:
        return [PastTerm(torch.zeros(0, dtype=torch.long, device=features.device),
                         features.new_zeros(0, shape[1]), shape) for shape in shapes]
    if (prune > 0 and compiled_ok(features, positions, displacements, probs, q)
            and features.dtype == positions.dtype == displacements.dtype == probs.dtype
            == q.dtype == torch.float32
            and all(proj.bias is None for proj, _ in projections)):
        # (a projection's bias would be added once per cell, not once per weighted triple)
        return _compiled_triple_terms(features, positions, displacements, probs, mask, q,
                                      prune, batch_index, projections, grid, shapes)
    if prune > 0:
        q = q * (q >= prune)
    cells = torch.floor(grid.xy_to_cell(positions[:, :, None, :]
                                        + displacements[:, None, :, :])).long()   # (M, P, K, 2)
    w = (probs * mask.to(probs.dtype))[:, :, None] * q[:, None, :]             # (M, P, K)
    way = _triple_terms if prune > 0 else _window_terms
    return way(features, positions, batch_index, projections, grid, shapes, cells, w)


def _window_terms(features: Tensor, positions: Tensor, batch_index: Tensor,
                  projections: Sequence[tuple[nn.Linear, Tensor | None]], grid: BEVGrid,
                  shapes: list[tuple[int, int, int, int]], cells: Tensor, w: Tensor
                  ) -> list[PastTerm]:
    """:func:`sparse_past_terms` per sample as a small matrix product: the weights of its
    ``P`` source cells over a local ``D x D`` window of destination cells (``D`` covers the
    largest displacement) accumulated first, then multiplied with the ``(P, C)`` features;
    only the window cells that receive a weight become rows (repeats across samples)."""
    M, P, _ = features.shape
    H, W = grid.H, grid.W
    centre = torch.floor(grid.xy_to_cell(positions[:, P // 2])).long()[:, None, :]   # (M, 1, 2)
    reach = int((cells - centre[:, None]).abs().amax().item())
    D = 2 * reach + 1
    local = cells - centre[:, None] + reach                                    # in [0, D)
    dest = local[..., 1] * D + local[..., 0]                                   # (M, P, K)
    Wm = w.new_zeros(M, D * D, P)
    src = torch.arange(P, device=w.device)[None, :, None].expand_as(dest)
    flat_idx = (dest * P + src).reshape(M, -1)
    Wm.view(M, -1).scatter_add_(1, flat_idx, w.reshape(M, -1))
    offs = torch.arange(D, device=w.device) - reach
    dr, dc = torch.meshgrid(offs, offs, indexing='ij')
    col = centre[:, 0, 0, None] + dc.reshape(1, -1)                            # (M, D*D)
    row = centre[:, 0, 1, None] + dr.reshape(1, -1)
    # only the window cells that receive a weight: the window spans the largest displacement
    # of any sample (bins pruned or not), and most of its cells add exactly zero
    ok = (col >= 0) & (col < W) & (row >= 0) & (row < H) & (Wm.amax(dim=2) > 0)
    flat = (batch_index[:, None] * H + row) * W + col
    terms = []
    for (projection, subset), shape in zip(projections, shapes):
        if subset is None:
            out_local = torch.bmm(Wm, projection(features))                    # (M, D*D, C)
            terms.append(PastTerm(flat[ok], out_local[ok], shape))
        else:
            out_local = torch.bmm(Wm[subset], projection(features[subset]))
            keep = ok[subset]
            terms.append(PastTerm(flat[subset][keep], out_local[keep], shape))
    return terms


def _triple_terms(features: Tensor, positions: Tensor, batch_index: Tensor,
                  projections: Sequence[tuple[nn.Linear, Tensor | None]], grid: BEVGrid,
                  shapes: list[tuple[int, int, int, int]], cells: Tensor, w: Tensor
                  ) -> list[PastTerm]:
    """:func:`sparse_past_terms` from the (sample, cell, bin) triples of non-zero weight that
    land on the map: their projected features times their weights, summed per destination
    cell (one row per cell the term touches)."""
    M = features.shape[0]
    H, W = grid.H, grid.W
    col, row = cells[..., 0], cells[..., 1]
    m, p, k = torch.nonzero((w > 0) & (col >= 0) & (col < W) & (row >= 0) & (row < H),
                            as_tuple=True)
    flat = (batch_index[m] * H + row[m, p, k]) * W + col[m, p, k]
    weight = w[m, p, k]
    terms = []
    for (projection, subset), shape in zip(projections, shapes):
        if subset is None:
            mm, pp, ff, ww = m, p, flat, weight
        elif len(subset) == 0:          # no sample of its own (a zero W2): nothing to project
            terms.append(PastTerm(flat[:0], features.new_zeros(0, shape[1]), shape))
            continue
        else:
            member = torch.zeros(M, dtype=torch.bool, device=features.device)
            member[subset] = True
            take = member[m]
            mm, pp, ff, ww = m[take], p[take], flat[take], weight[take]
        values = projection(features)[mm, pp] * ww[:, None]                  # (T, C)
        cells_hit, where = torch.unique(ff, return_inverse=True)
        rows = values.new_zeros(len(cells_hit), shape[1]).index_add_(0, where, values)
        terms.append(PastTerm(cells_hit, rows, shape, distinct=True))
    return terms


def _compiled_triple_terms(features: Tensor, positions: Tensor, displacements: Tensor,
                           probs: Tensor, mask: Tensor, q: Tensor, prune: float,
                           batch_index: Tensor,
                           projections: Sequence[tuple[nn.Linear, Tensor | None]],
                           grid: BEVGrid, shapes: list[tuple[int, int, int, int]]
                           ) -> list[PastTerm]:
    """:func:`_triple_terms` on the CPU without autograd: the triples' destinations and
    weights found and the weighted features summed per destination cell in one compiled pass
    (:func:`suit_ros.ops.kernels.sum_triples`), then each cell's sum projected once
    (``W2 sum w f`` where the tensor code sums ``w W2 f``: the same up to float rounding,
    tested), each projection over the samples it names."""
    from suit_ros.ops.kernels import sum_triples
    M, P, _ = features.shape
    K = q.shape[1]
    # the compiled pass reads these unchecked
    if (positions.shape != (M, P, 2) or displacements.shape != (M, K, 2)
            or probs.shape != (M, P) or mask.shape != (M, P) or batch_index.shape != (M,)):
        raise ValueError(f'sparse past term: features {tuple(features.shape)}, positions '
                         f'{tuple(positions.shape)}, displacements {tuple(displacements.shape)},'
                         f' q {tuple(q.shape)}, probs {tuple(probs.shape)}, mask '
                         f'{tuple(mask.shape)}, batch index {tuple(batch_index.shape)}')
    member = np.zeros((len(projections), M), np.bool_)
    for s, (_, subset) in enumerate(projections):
        if subset is None:
            member[s] = True
        else:
            member[s, subset.cpu().numpy()] = True
    flat, sums, counts = sum_triples(
        positions.contiguous().numpy(), displacements.contiguous().numpy(),
        probs.contiguous().numpy(), mask.to(torch.bool).contiguous().numpy(),
        q.contiguous().numpy(), np.float32(prune), *grid.origin_and_cell(),
        batch_index.to(torch.int64).contiguous().numpy(), features.contiguous().numpy(),
        member, grid.H, grid.W)
    terms = []
    start = 0
    for (projection, _), shape, n in zip(projections, shapes, counts.tolist()):
        rows = F.linear(torch.from_numpy(sums[start:start + n]), projection.weight,
                        projection.bias)
        terms.append(PastTerm(torch.from_numpy(flat[start:start + n]), rows, shape,
                              distinct=True))
        start += n
    return terms


def warp_dense(previous: Tensor, T_prev_now: NDArray[np.float64], grid: BEVGrid) -> Tensor:
    """Warp a whole previous BEV map into the current frame (bilinear), ``(B, C, H, W)``."""
    B = previous.shape[0]
    centres = grid.cell_centres(previous.device).double()                     # (H, W, 2)
    T = torch.from_numpy(np.ascontiguousarray(T_prev_now)).to(previous.device)  # (B, 4, 4)
    xy = torch.einsum('bij,hwj->bhwi', T[:, :2, :2], centres) + T[:, None, None, :2, 3]
    x0, y0, _, x1, y1, _ = grid.point_range
    u = (xy[..., 0] - x0) / (x1 - x0) * 2 - 1
    v = (xy[..., 1] - y0) / (y1 - y0) * 2 - 1
    sample_grid = torch.stack([u, v], dim=-1).to(previous.dtype)
    return F.grid_sample(previous, sample_grid, mode='bilinear', padding_mode='zeros',
                         align_corners=False).view(B, *previous.shape[1:])
