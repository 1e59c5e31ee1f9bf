//! Winograd F(2x2, 3x3) and F(4x4, 3x3),
//! [`ConvAlgo::Winograd2`](super::ConvAlgo::Winograd2) and
//! [`ConvAlgo::Winograd4`](super::ConvAlgo::Winograd4): the weight transform
//! ([`pack_winograd`], once, at packing), and per block of tile rows the input transform,
//! one GEMM per transformed position and the output transform with the epilogue
//! ([`winograd_part`]). A LoRA branch's `A`, transformed like the weight, multiplies the
//! same transformed tiles (`G = Ã V`, rank rows per position, in registers after the
//! input transform: [`project`]); `G` is output-transformed like `rank` more output
//! channels and each output channel adds `Σ_k B[c][k] (Aᵀ G_k A)`, a rank-`rank` update
//! on M·M instead of A·A values per tile (the transform is linear). Before, `B G` was one
//! GEMM of inner size `rank` per position (16 or 36 per block), far below the GEMM
//! library's efficient sizes. Under a split by channels the parts share one transform
//! and each sums `G` over its share of the channels ([`winograd_shared`]).
//!
//! The transforms are plain Rust on fixed-size lane arrays ([`Lanes`]), run inside pulp
//! `WithSimd` bodies ([`InputTransform`], [`OutputTransform`]) so that they are compiled
//! for the widest SIMD the CPU has: everything they call is `#[inline(always)]`.

use std::marker::PhantomData;

use rayon::prelude::*;

use super::split::{Part, channel_shares, shared_scratch, sum_shares};
use super::{Conv2dShape, Lora, finish};
use crate::kernels::Epilogue;
use crate::kernels::gemm::{MatMut, MatRef, few_rows_product, sgemm};

/// F(2x2, 3x3) weight transform `G` (4x3).
pub(super) const F2_G: [[f64; 3]; 4] = [[1.0, 0.0, 0.0], [0.5, 0.5, 0.5], [0.5, -0.5, 0.5], [0.0, 0.0, 1.0]];

/// F(4x4, 3x3) weight transform `G` (6x3). Interpolation points 0, 1, −1, 1/2, −2, ∞
/// rather than the usual 0, ±1, ±2, ∞: in f32 their rounding error is about a third
/// (Barabasz et al., "Error analysis and improving the accuracy of Winograd convolution
/// for deep neural networks", 2020). Rows are scaled so that `Bᵀ` has small integers.
pub(super) const F4_G: [[f64; 3]; 6] = [
    [1.0 / 2.0, 0.0, 0.0],
    [1.0 / 6.0, 1.0 / 6.0, 1.0 / 6.0],
    [1.0 / 6.0, -1.0 / 6.0, 1.0 / 6.0],
    [16.0 / 15.0, 8.0 / 15.0, 4.0 / 15.0],
    [1.0 / 30.0, -2.0 / 30.0, 4.0 / 30.0],
    [0.0, 0.0, 1.0 / 2.0],
];

/// `L` floats processed as one unit by the transforms; fixed-size array arithmetic that
/// the compiler turns into SIMD instructions.
#[derive(Clone, Copy)]
pub(super) struct Lanes<const L: usize>([f32; L]);

impl<const L: usize> Lanes<L> {
    #[inline(always)]
    fn load(s: &[f32]) -> Self {
        Lanes(s[..L].try_into().expect("L floats"))
    }
    #[inline(always)]
    fn store(&self, s: &mut [f32]) {
        s[..L].copy_from_slice(&self.0);
    }
    #[inline(always)]
    fn zip(self, o: Self, f: impl Fn(f32, f32) -> f32) -> Self {
        Lanes(std::array::from_fn(|i| f(self.0[i], o.0[i])))
    }
    /// `acc + a · self`, fused (one rounding).
    #[inline(always)]
    fn mul_add(self, a: f32, acc: Self) -> Self {
        Lanes(std::array::from_fn(|i| self.0[i].mul_add(a, acc.0[i])))
    }
}

impl<const L: usize> std::ops::Add for Lanes<L> {
    type Output = Self;
    #[inline(always)]
    fn add(self, o: Self) -> Self {
        self.zip(o, |a, b| a + b)
    }
}

impl<const L: usize> std::ops::Sub for Lanes<L> {
    type Output = Self;
    #[inline(always)]
    fn sub(self, o: Self) -> Self {
        self.zip(o, |a, b| a - b)
    }
}

impl<const L: usize> std::ops::Mul<Lanes<L>> for f32 {
    type Output = Lanes<L>;
    #[inline(always)]
    fn mul(self, o: Lanes<L>) -> Lanes<L> {
        Lanes(o.0.map(|v| self * v))
    }
}

/// The 1-D input (`Bᵀ d`) and output (`Aᵀ m`) transforms of F(M, 3), `A = M + 2`, applied
/// lane-wise.
pub(super) trait WinoTf<const A: usize, const M: usize> {
    fn bt<const L: usize>(d: [Lanes<L>; A]) -> [Lanes<L>; A];
    fn at<const L: usize>(m: [Lanes<L>; A]) -> [Lanes<L>; M];
}

pub(super) struct F2;
pub(super) struct F4;

impl WinoTf<4, 2> for F2 {
    #[inline(always)]
    fn bt<const L: usize>(d: [Lanes<L>; 4]) -> [Lanes<L>; 4] {
        [d[0] - d[2], d[1] + d[2], d[2] - d[1], d[1] - d[3]]
    }
    #[inline(always)]
    fn at<const L: usize>(m: [Lanes<L>; 4]) -> [Lanes<L>; 2] {
        [m[0] + m[1] + m[2], m[1] - m[2] - m[3]]
    }
}

impl WinoTf<6, 4> for F4 {
    #[inline(always)]
    fn bt<const L: usize>(d: [Lanes<L>; 6]) -> [Lanes<L>; 6] {
        let (p14, m13, m24) = (d[1] + d[4], d[1] - d[3], d[2] - d[4]);
        [
            2.0 * (d[0] + d[4]) - 3.0 * m13 - 4.0 * d[2],
            2.0 * (d[4] - d[1]) + d[2] + 5.0 * d[3],
            5.0 * d[2] - 2.0 * p14 - d[3],
            2.0 * m13 + d[2] - d[4],
            d[1] - d[3] - 2.0 * m24,
            2.0 * (d[1] + d[5]) - 3.0 * m24 - 4.0 * d[3],
        ]
    }
    #[inline(always)]
    fn at<const L: usize>(m: [Lanes<L>; 6]) -> [Lanes<L>; 4] {
        let (p, n) = (m[1] + m[2], m[1] - m[2]);
        [
            m[0] + p + m[3] + m[4],
            n + 0.5 * m[3] - 2.0 * m[4],
            p + 0.25 * m[3] + 4.0 * m[4],
            n + 0.125 * m[3] - 8.0 * m[4] + m[5],
        ]
    }
}

/// `U[ξ][co][ci] = (G g Gᵀ)[ξ]` for each 3x3 kernel `g`, computed in f64.
///
/// 32 kernels of consecutive input channels at a time, in lanes: each of the `A x A`
/// outputs is then 32 consecutive floats of its row, where one kernel at a time wrote
/// `A x A` floats a row apart (rows of `cout · cin` floats: at 256 input channels and 4
/// output channels, a LoRA `A`, every write hit the same cache set). Run at every switch
/// for a variant's raw LoRA `A` (`Bound::pack_lora`), so its speed is the first run's.
pub(super) fn pack_winograd<const A: usize>(s: &Conv2dShape, g_mat: &[[f64; 3]; A], weight: &[f32], out: &mut [f32]) {
    pulp::Arch::new().dispatch(PackWinograd { s, g_mat, weight, out });
}

struct PackWinograd<'a, const A: usize> {
    s: &'a Conv2dShape,
    g_mat: &'a [[f64; 3]; A],
    weight: &'a [f32],
    out: &'a mut [f32],
}

impl<const A: usize> pulp::WithSimd for PackWinograd<'_, A> {
    type Output = ();
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        const L: usize = 32;
        let PackWinograd { s, g_mat, weight, out } = self;
        let cin_g = s.cin_g();
        let plane = s.cout * cin_g;
        for co in 0..s.cout {
            for ci0 in (0..cin_g).step_by(L) {
                let n = L.min(cin_g - ci0);
                // The nine taps of `n` kernels, lane `l` the kernel of input channel ci0 + l.
                let mut g = [[0.0f64; L]; 9];
                for l in 0..n {
                    let k = &weight[(co * cin_g + ci0 + l) * 9..][..9];
                    for (tap, &v) in g.iter_mut().zip(k) {
                        tap[l] = f64::from(v);
                    }
                }
                // t = G g (A x 3), then u = t Gᵀ (A x A), each sum in the order r = 0, 1, 2.
                let mut t = [[[0.0f64; L]; 3]; A];
                for (i, ti) in t.iter_mut().enumerate() {
                    let gi = g_mat[i];
                    for (j, tij) in ti.iter_mut().enumerate() {
                        for l in 0..L {
                            tij[l] = gi[0] * g[j][l] + gi[1] * g[3 + j][l] + gi[2] * g[6 + j][l];
                        }
                    }
                }
                for (i, ti) in t.iter().enumerate() {
                    for (j, gj) in g_mat.iter().enumerate() {
                        let row = &mut out[(i * A + j) * plane + co * cin_g + ci0..][..n];
                        for (l, o) in row.iter_mut().enumerate() {
                            *o = (ti[0][l] * gj[0] + ti[1][l] * gj[1] + ti[2][l] * gj[2]) as f32;
                        }
                    }
                }
            }
        }
    }
}

/// Lanes of the input transform for `tx` tiles across, the widest that wastes at most a
/// quarter (it works one tile row at a time, and small images have few tiles per row).
fn in_lanes(tx: usize) -> usize {
    match tx {
        12.. => 16,
        6.. => 8,
        _ => 4,
    }
}

/// Lanes of the output transform (all tiles of a block at once): one AVX-512 register.
const OUT_LANES: usize = 16;

/// Sizes of one thread's Winograd scratch.
pub(super) struct Wino {
    /// Tiles across a row of the output.
    tx: usize,
    /// Tile rows per block (one block = one set of GEMMs).
    pub(super) rows: usize,
    /// Lanes of the input transform, [`in_lanes`].
    lanes: usize,
    /// Length of one input-phase row: room for whole-lane loads at offset 1.
    plen: usize,
    alpha: usize,
    cin_g: usize,
    cout_g: usize,
}

impl Wino {
    pub(super) fn new<const A: usize, const M: usize>(s: &Conv2dShape) -> Wino {
        let tx = s.ow.div_ceil(M);
        let (cin_g, cout_g) = (s.cin_g(), s.cout_g());
        // V and M of a block fill up to 2 MiB (larger blocks make for fewer, larger GEMMs;
        // this costs more than L2 but measured faster); at least one tile row per block.
        let per_tile = (cin_g + cout_g) * A * A;
        let tiles = (512 * 1024 / per_tile.max(1)).max(16);
        let rows = (tiles / tx).clamp(1, s.oh.div_ceil(M));
        let lanes = in_lanes(tx);
        // Whole-lane loads reach one past the last whole-lane group of tiles; M·plen is a
        // whole number of lanes, for the vertical pass.
        let plen = (tx.div_ceil(lanes) * lanes + 1).next_multiple_of((lanes / M).max(1));
        Wino { tx, rows, lanes, plen, alpha: A, cin_g, cout_g }
    }

    /// Transformed positions (`A·A`).
    fn positions(&self) -> usize {
        self.alpha * self.alpha
    }

    /// Tiles per block.
    fn block(&self) -> usize {
        self.rows * self.tx
    }

    /// Row stride of V and M: the block plus room for whole-lane stores past its end.
    fn stride(&self) -> usize {
        self.block() + OUT_LANES.max(self.lanes)
    }

    /// Floats per channel of V, M and G (`A·A` rows of [`Self::stride`]), padded to an odd
    /// number of cache lines: the GEMMs read and write them a column at a time (one row
    /// per channel), and with an even number (2304 floats for F(4x4) at a block of 16
    /// tiles) the channels of a column fall into an eighth of the L1 sets.
    fn chan(&self) -> usize {
        (self.alpha * self.alpha * self.stride()).next_multiple_of(32) + 16
    }

    /// Transform work space: the input transform's A·M phase rows and their A·M vertical
    /// transforms; the output transform's A·M + M·M rows of a block.
    fn work(&self) -> usize {
        let (a, m) = (self.alpha, self.alpha - 2);
        let input = 2 * a * m * self.plen;
        let output = (a * m + m * m) * self.stride();
        input.max(output)
    }

    /// With `rank` rows of a LoRA branch's `G = Ã V` (twice: under a channel split, the
    /// part's share of it too) and their output transforms (0: none).
    pub(super) fn scratch(&self, rank: usize) -> usize {
        let m = self.alpha - 2;
        (self.cin_g + self.cout_g + 2 * rank) * self.chan() + rank * m * m * self.stride() + self.work()
    }
}

/// Winograd over one part: its tile rows in blocks; per block and group: input transform
/// into `V[ci][ξ][t]`, one GEMM per ξ into `Mt[co][ξ][t]` (plus `B (Ã V)` for a LoRA
/// branch), output transform + epilogue.
pub(super) fn winograd_part<T: WinoTf<A, M>, const A: usize, const M: usize>(
    s: &Conv2dShape,
    u: &[f32],
    lora: Option<&Lora>,
    ep: &Epilogue,
    x: &[f32],
    part: &mut Part,
    scratch: &mut [f32],
) {
    let wz = Wino::new::<A, M>(s);
    let (cin_g, cout_g, tx) = (s.cin_g(), s.cout_g(), wz.tx);
    let ty_n = s.oh.div_ceil(M);
    let (ts, cs) = (wz.stride(), wz.chan());
    let (v, rest) = scratch.split_at_mut(cin_g * cs);
    let (mt, rest) = rest.split_at_mut(cout_g * cs);
    let rank = lora.map_or(0, |l| l.rank);
    let (gl, rest) = rest.split_at_mut(rank * cs);
    let (yg, work) = rest.split_at_mut(rank * M * M * ts);
    // Global tile rows (image · ty_n + ty) of this part; its boundaries are whole tile rows.
    let tile_row = |r: usize| (r / s.oh) * ty_n + (r % s.oh).div_ceil(M);
    let (u0, u1) = (tile_row(part.r0), tile_row(part.r1));
    let mut b0 = u0;
    while b0 < u1 {
        let b1 = (b0 + wz.rows).min(u1);
        let tb = (b1 - b0) * tx;
        for g in 0..s.groups {
            let chans = part.channels_of(g, cout_g);
            let mrows = chans.len();
            if mrows == 0 {
                continue;
            }
            let blocks = b0..b1;
            pulp::Arch::new().dispatch(InputTransform::<T, A, M> {
                s,
                wz: &wz,
                x,
                g,
                blocks,
                cis: 0..cin_g,
                v,
                work,
                tf: PhantomData,
            });
            // One group (checked) for a LoRA branch: Ã is `[ξ][rank][cin]`.
            let lora = lora.map(|l| LoraOut { b: l.b, rank, g: project(&wz, l, 0..cin_g, v, tb, gl), y: &mut *yg });
            gemms_and_output::<T, A, M>(s, &wz, u, v, mt, chans, (b0, tb), part, ep, lora, work);
        }
        b0 = b1;
    }
}

/// A LoRA branch's `G[k][ξ][t] = Σ_ci Ã[ξ][k][ci] V[ci][ξ][t]` over the `tb` tiles of a
/// block and the input channels `cis` (one group), whose transformed rows `v` holds
/// from its start, into `g` (laid out as `V`, by rank instead of channel): per position,
/// the rank rows of `Ã` times `V` in registers ([`few_rows_product`]). Through the input
/// transform, 8 channels at a time, a rank-4 branch took 9.5% of ResNet-18's 14x14
/// F(2x2) layer at one thread; this way 3.5%.
fn project<'g>(wz: &Wino, l: &Lora, cis: std::ops::Range<usize>, v: &[f32], tb: usize, g: &'g mut [f32]) -> &'g [f32] {
    let (cin_g, ts, cs, rank) = (wz.cin_g, wz.stride(), wz.chan(), l.rank);
    for xi in 0..wz.positions() {
        let a = &l.a[xi * rank * cin_g + cis.start..];
        let lhs = MatRef { data: a, rows: rank, cols: cis.len(), row_stride: cin_g, col_stride: 1 };
        let rhs = MatRef { data: &v[xi * ts..], rows: cis.len(), cols: tb, row_stride: cs, col_stride: 1 };
        let dst = MatMut { data: &mut g[xi * ts..], rows: rank, cols: tb, row_stride: cs, col_stride: 1 };
        few_rows_product(lhs, rhs, dst);
    }
    g
}

/// A block's GEMMs, one per transformed position, for output channels `chans` of one
/// group from its transformed input `v`, into `mt`; then their output transform and
/// epilogue into `part`.
#[allow(clippy::too_many_arguments)]
fn gemms_and_output<T: WinoTf<A, M>, const A: usize, const M: usize>(
    s: &Conv2dShape,
    wz: &Wino,
    u: &[f32],
    v: &[f32],
    mt: &mut [f32],
    chans: std::ops::Range<usize>,
    (b0, tb): (usize, usize),
    part: &mut Part,
    ep: &Epilogue,
    lora: Option<LoraOut>,
    work: &mut [f32],
) {
    let (cin_g, ts, cs, mrows) = (s.cin_g(), wz.stride(), wz.chan(), chans.len());
    for xi in 0..A * A {
        let lhs = MatRef::row_major(&u[(xi * s.cout + chans.start) * cin_g..][..mrows * cin_g], mrows, cin_g);
        let rhs = MatRef { data: &v[xi * ts..], rows: cin_g, cols: tb, row_stride: cs, col_stride: 1 };
        let dst = MatMut { data: &mut mt[xi * ts..], rows: mrows, cols: tb, row_stride: cs, col_stride: 1 };
        sgemm(lhs, rhs, dst, false, 1);
    }
    let mt = &*mt;
    pulp::Arch::new().dispatch(OutputTransform::<T, A, M> {
        s,
        wz,
        mt,
        tb,
        b0,
        chans,
        part,
        ep,
        lora,
        work,
        tf: PhantomData,
    });
}

/// Winograd over parts that split a layer of one group by output channels (each part
/// owns every tile row): per block, the parts first transform the input together, each
/// its share of the input channels into one `V` (in the first part's scratch), then each
/// runs its channels' GEMMs and output transform from that `V`. A LoRA branch's
/// projection `G = Ã V` sums every input channel: each part sums its share's rows of `V`
/// right after transforming them ([`project`]), and every part adds the shares up.
/// Through [`winograd_part`] each part would transform the whole input itself: ResNet-50's
/// 28x28 3x3 layers (49 tiles) scaled 1.36-1.46x from one thread to two, its 14x14 ones
/// 1.39-1.67x. `jobs` are the parts with their scratch, each at least
/// [`Wino::scratch`]`(0)` floats.
pub(super) fn winograd_shared<T: WinoTf<A, M>, const A: usize, const M: usize>(
    s: &Conv2dShape,
    u: &[f32],
    lora: Option<&Lora>,
    ep: &Epilogue,
    x: &[f32],
    jobs: &mut [(Part, &mut [f32])],
) {
    let wz = Wino::new::<A, M>(s);
    let (cin_g, cout_g, cs) = (s.cin_g(), s.cout_g(), wz.chan());
    assert_eq!(s.groups, 1, "winograd_shared: one group");
    let threads = jobs.len();
    // Every part's rows are the whole output's (checked by `shared_scratch`).
    let (r0, r1) = (jobs[0].0.r0, jobs[0].0.r1);
    // Each job's scratch: its own V region (the first job's is the shared V), then `mt`
    // and the transforms' work space, and at its end its share of a LoRA branch's `G`.
    let rank = lora.map_or(0, |l| l.rank);
    let (v_shared, mut shares_g, mut own) = shared_scratch(jobs, 0, cin_g * cs, rank * cs);
    let ty_n = s.oh.div_ceil(M);
    let tile_row = |r: usize| (r / s.oh) * ty_n + (r % s.oh).div_ceil(M);
    let (u0, u1) = (tile_row(r0), tile_row(r1));
    let mut b0 = u0;
    while b0 < u1 {
        let b1 = (b0 + wz.rows).min(u1);
        let tb = (b1 - b0) * wz.tx;
        {
            // Each job transforms a share of the input channels into its rows of V (and
            // sums their part of a LoRA branch's projection).
            let shares = channel_shares(v_shared, cin_g, threads, cs);
            let jobs = shares.into_par_iter().zip(own.par_iter_mut()).zip(shares_g.par_iter_mut());
            jobs.for_each(|(((cis, v), (_, _, rest)), share_g)| {
                let work = &mut rest[cout_g * cs..];
                pulp::Arch::new().dispatch(InputTransform::<T, A, M> {
                    s,
                    wz: &wz,
                    x,
                    g: 0,
                    blocks: b0..b1,
                    cis: cis.clone(),
                    v,
                    work,
                    tf: PhantomData,
                });
                if let Some(l) = lora {
                    project(&wz, l, cis, v, tb, share_g);
                }
            });
        }
        let (v, shares_g): (&[f32], &[&mut [f32]]) = (v_shared, &shares_g);
        let ts = wz.stride();
        own.par_iter_mut().for_each(|(part, _, rest)| {
            let (mt, rest) = rest.split_at_mut(cout_g * cs);
            let (gl, rest) = rest.split_at_mut(rank * cs);
            let (yg, work) = rest.split_at_mut(rank * M * M * ts);
            let chans = part.channels_of(0, cout_g);
            if chans.is_empty() {
                return;
            }
            let lora = lora.map(|l| {
                sum_shares(gl, shares_g);
                LoraOut { b: l.b, rank, g: &*gl, y: yg }
            });
            gemms_and_output::<T, A, M>(s, &wz, u, v, mt, chans, (b0, tb), part, ep, lora, work);
        });
        b0 = b1;
    }
}

/// The input transform of tile rows `blocks` (of a block), every input channel of group
/// `g`, into `v[ci][ξ][t]`; compiled for the widest SIMD the CPU has.
struct InputTransform<'a, T, const A: usize, const M: usize> {
    s: &'a Conv2dShape,
    wz: &'a Wino,
    x: &'a [f32],
    g: usize,
    blocks: std::ops::Range<usize>,
    /// The input channels (of the group) to transform; `v` starts at the first.
    cis: std::ops::Range<usize>,
    v: &'a mut [f32],
    work: &'a mut [f32],
    tf: PhantomData<T>,
}

impl<T: WinoTf<A, M>, const A: usize, const M: usize> pulp::WithSimd for InputTransform<'_, T, A, M> {
    type Output = ();
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        match self.wz.lanes {
            16 => self.run::<16>(),
            8 => self.run::<8>(),
            _ => self.run::<4>(),
        }
    }
}

impl<T: WinoTf<A, M>, const A: usize, const M: usize> InputTransform<'_, T, A, M> {
    #[inline(always)]
    fn run<const L: usize>(self) {
        let InputTransform { s, wz, x, g, blocks, cis, v, work, .. } = self;
        let (cin_g, ty_n, cs) = (s.cin_g(), s.oh.div_ceil(M), wz.chan());
        for ci in cis.clone() {
            let vc = &mut v[(ci - cis.start) * cs..][..cs];
            for gu in blocks.clone() {
                let (n, ty) = (gu / ty_n, gu % ty_n);
                let xc = &x[(n * s.cin + g * cin_g + ci) * s.h * s.w..][..s.h * s.w];
                input_row::<T, A, M, L>(s, wz, xc, ty, vc, (gu - blocks.start) * wz.tx, work);
            }
        }
    }
}

/// A LoRA branch at the output transform: `B` (`[cout][rank]`), `G = Ã V` of the block
/// (`g[k][ξ][t]`) and room for its output transforms `y[k][r][col][t]`, added to each
/// output channel's as the rank-`rank` update `Σ_k B[c][k] y[k]` (the transform is
/// linear, so this is `Aᵀ (B G) A` with `M·M` instead of `A·A` products per tile).
struct LoraOut<'a> {
    b: &'a [f32],
    rank: usize,
    g: &'a [f32],
    y: &'a mut [f32],
}

/// The output transform and epilogue of a block (`tb` tiles from global tile row `b0`)
/// for output channels `chans`, from `mt[co][ξ][t]` (plus a LoRA branch's update);
/// compiled for the widest SIMD the CPU has.
struct OutputTransform<'a, 'p, T, const A: usize, const M: usize> {
    s: &'a Conv2dShape,
    wz: &'a Wino,
    mt: &'a [f32],
    tb: usize,
    b0: usize,
    chans: std::ops::Range<usize>,
    part: &'a mut Part<'p>,
    ep: &'a Epilogue<'a>,
    lora: Option<LoraOut<'a>>,
    work: &'a mut [f32],
    tf: PhantomData<T>,
}

impl<T: WinoTf<A, M>, const A: usize, const M: usize> pulp::WithSimd for OutputTransform<'_, '_, T, A, M> {
    type Output = ();
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        let OutputTransform { s, wz, mt, tb, b0, chans, part, ep, lora, work, .. } = self;
        let (ts, plane) = (wz.stride(), M * M * wz.stride());
        let lora = lora.map(|l| {
            let (sbuf, _) = work.split_at_mut(A * M * ts);
            for (gk, yk) in l.g.chunks(wz.chan()).zip(l.y.chunks_mut(plane)).take(l.rank) {
                transform_out::<T, A, M>(gk, tb, ts, sbuf, yk);
            }
            (l.b, l.rank, &*l.y)
        });
        for (c, mc) in chans.zip(mt.chunks(wz.chan())) {
            let lora = lora.map(|(b, rank, y)| (&b[c * rank..][..rank], y));
            output_block::<T, A, M>(s, wz, mc, tb, b0, c, part, ep, lora, work);
        }
    }
}

/// Input transform of one tile row `ty` of one channel plane `xc`, into `vc[ξ][t0 + tx]`
/// (row stride `wz.stride()`). Vectorised across the tiles of the row: the padded input
/// rows are split into M phases (phase q holds columns q, q+M, ..), so that column j of
/// every tile is the contiguous run `phase[j % M][j / M..]`.
#[inline(always)]
fn input_row<T: WinoTf<A, M>, const A: usize, const M: usize, const L: usize>(
    s: &Conv2dShape,
    wz: &Wino,
    xc: &[f32],
    ty: usize,
    vc: &mut [f32],
    t0: usize,
    work: &mut [f32],
) {
    let (plen, ts) = (wz.plen, wz.stride());
    let (ph, rest) = work.split_at_mut(A * M * plen);
    let tv = &mut rest[..A * M * plen];
    // ph[j][q][u] = padded input (row ty·M + j, column u·M + q), straight from the input
    // row: through a padded copy of the row, the next loop's loads stalled on forwarding
    // from the copy's stores.
    for (j, phj) in ph.chunks_mut(M * plen).enumerate() {
        let iy = (ty * M + j) as isize - s.pad_h as isize;
        if iy < 0 || iy as usize >= s.h {
            phj.fill(0.0);
            continue;
        }
        let row = iy as usize * s.w;
        let src = &xc[row..][..s.w];
        // Tiles u whose M columns u·M + q − pad all lie inside the row: ua..ub. They are
        // copied in groups of L tiles, which LLVM unrolls into straight-line moves (rows
        // have fewer tiles than its 16-lane vector loop needs, which left them to a
        // slower remainder loop; the vector loop itself, forced, measured slower still).
        // A group may read past the row (into the next; not past the plane) and past
        // `ub`: the edges below then overwrite what it wrote there.
        let ua = s.pad_w.div_ceil(M).min(plen);
        let ub = ((s.w + s.pad_w) / M).clamp(ua, plen);
        let mut u = ua;
        while u < ub && u + L <= plen && row + u * M - s.pad_w + L * M <= xc.len() {
            let start = row + u * M - s.pad_w;
            deinterleave::<M>(&xc[start..start + L * M], phj, plen, u);
            u += L;
        }
        // The inside tiles the groups left (none when a row is narrower than a tile, where
        // `ub · M − pad` may lie past the row).
        if u < ub {
            deinterleave::<M>(&src[u * M - s.pad_w..ub * M - s.pad_w], phj, plen, u);
        }
        // The edges. Phase columns past `tx` only feed lanes past the last tile, whose
        // results are overwritten or never read: left as they are.
        for u in (0..ua).chain(ub..(wz.tx + 1).min(plen)) {
            for q in 0..M {
                let col = (u * M + q).checked_sub(s.pad_w).filter(|&c| c < s.w);
                phj[q * plen + u] = col.map_or(0.0, |c| src[c]);
            }
        }
    }
    // Vertical, column-wise (phases are just a column order): tv[i] = Σ_j Bᵀ[i][j] ph[j].
    for c in (0..M * plen).step_by(L) {
        let o = T::bt::<L>(std::array::from_fn(|j| Lanes::load(&ph[j * M * plen + c..])));
        for (i, oi) in o.iter().enumerate() {
            oi.store(&mut tv[i * M * plen + c..]);
        }
    }
    // Horizontal, L tiles at a time: column j of tile t is tv[i][j % M][t + j / M].
    // Lanes past the row's last tile spill into the next tile row's columns, which are
    // written after this one, or into the slack at the end of V's rows.
    for i in 0..A {
        let tvi = &tv[i * M * plen..][..M * plen];
        for t in (0..wz.tx).step_by(L) {
            let o = T::bt::<L>(std::array::from_fn(|j| Lanes::load(&tvi[(j % M) * plen + t + j / M..])));
            for (k, ok) in o.iter().enumerate() {
                ok.store(&mut vc[(i * A + k) * ts + t0 + t..]);
            }
        }
    }
}

/// `ph[q·plen + u0 + u] = row[u·M + q]` for the M phases (a transpose the compiler
/// vectorises, with shuffles, when each phase is its own slice; only whole vectors of
/// tiles, the rest is scalar).
#[inline(always)]
fn deinterleave<const M: usize>(row: &[f32], ph: &mut [f32], plen: usize, u0: usize) {
    let n = row.len() / M;
    match M {
        2 => {
            let (p0, p1) = ph.split_at_mut(plen);
            let (p0, p1) = (&mut p0[u0..u0 + n], &mut p1[u0..u0 + n]);
            for (u, c) in row.chunks_exact(2).enumerate() {
                p0[u] = c[0];
                p1[u] = c[1];
            }
        }
        4 => {
            let (p0, rest) = ph.split_at_mut(plen);
            let (p1, rest) = rest.split_at_mut(plen);
            let (p2, p3) = rest.split_at_mut(plen);
            let (p0, p1) = (&mut p0[u0..u0 + n], &mut p1[u0..u0 + n]);
            let (p2, p3) = (&mut p2[u0..u0 + n], &mut p3[u0..u0 + n]);
            let row = &row[..4 * n];
            for u in 0..n {
                p0[u] = row[4 * u];
                p1[u] = row[4 * u + 1];
                p2[u] = row[4 * u + 2];
                p3[u] = row[4 * u + 3];
            }
        }
        _ => unreachable!("Winograd tiles are 2 or 4 wide"),
    }
}

/// `row[t·M + col] = y[col·stride + t]`, the inverse of [`deinterleave`].
#[inline(always)]
fn interleave<const M: usize>(y: &[f32], stride: usize, row: &mut [f32]) {
    let n = row.len() / M;
    match M {
        2 => {
            let (y0, y1) = (&y[..n], &y[stride..stride + n]);
            for (u, c) in row.chunks_exact_mut(2).enumerate() {
                c[0] = y0[u];
                c[1] = y1[u];
            }
        }
        4 => {
            let (y0, y1, y2, y3) = (&y[..n], &y[stride..][..n], &y[2 * stride..][..n], &y[3 * stride..][..n]);
            let row = &mut row[..4 * n];
            for u in 0..n {
                row[4 * u] = y0[u];
                row[4 * u + 1] = y1[u];
                row[4 * u + 2] = y2[u];
                row[4 * u + 3] = y3[u];
            }
        }
        _ => unreachable!("Winograd tiles are 2 or 4 wide"),
    }
}

/// The output transform `ybuf[r][col][t]` of one channel's `mc[ξ][t]` over a block of
/// `tb` tiles (rows `ts` apart), in whole lanes, through `sbuf`.
#[inline(always)]
fn transform_out<T: WinoTf<A, M>, const A: usize, const M: usize>(
    mc: &[f32],
    tb: usize,
    ts: usize,
    sbuf: &mut [f32],
    ybuf: &mut [f32],
) {
    const L: usize = OUT_LANES;
    // Horizontal: sbuf[i][col][t] = Σ_k Aᵀ[col][k] m[i][k][t].
    for i in 0..A {
        for t in (0..tb).step_by(L) {
            let o = T::at::<L>(std::array::from_fn(|k| Lanes::load(&mc[(i * A + k) * ts + t..])));
            for (col, oc) in o.iter().enumerate() {
                oc.store(&mut sbuf[(i * M + col) * ts + t..]);
            }
        }
    }
    // Vertical: ybuf[r][col][t] = Σ_i Aᵀ[r][i] sbuf[i][col][t].
    for col in 0..M {
        for t in (0..tb).step_by(L) {
            let o = T::at::<L>(std::array::from_fn(|i| Lanes::load(&sbuf[(i * M + col) * ts + t..])));
            for (r, or) in o.iter().enumerate() {
                or.store(&mut ybuf[(r * M + col) * ts + t..]);
            }
        }
    }
}

/// Output transform of one output channel over a whole block (`tb` tiles starting at
/// global tile row `b0`), from `mc[ξ][t]`, plus a LoRA branch's `Σ_k b[k] y[k]` (`b` the
/// channel's row of `B`, `y` the transformed `G`), then the epilogue into the part's
/// plane.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn output_block<T: WinoTf<A, M>, const A: usize, const M: usize>(
    s: &Conv2dShape,
    wz: &Wino,
    mc: &[f32],
    tb: usize,
    b0: usize,
    c: usize,
    part: &mut Part,
    ep: &Epilogue,
    lora: Option<(&[f32], &[f32])>,
    work: &mut [f32],
) {
    const L: usize = OUT_LANES;
    let ts = wz.stride();
    let (sbuf, rest) = work.split_at_mut(A * M * ts);
    let ybuf = &mut rest[..M * M * ts];
    transform_out::<T, A, M>(mc, tb, ts, sbuf, ybuf);
    if let Some((b, y)) = lora {
        let plane = M * M * ts;
        for j in 0..M * M {
            for t in (0..tb).step_by(L) {
                let o = j * ts + t;
                let acc = b.iter().enumerate().fold(Lanes::<L>::load(&ybuf[o..]), |acc, (k, &bk)| {
                    Lanes::load(&y[k * plane + o..]).mul_add(bk, acc)
                });
                acc.store(&mut ybuf[o..]);
            }
        }
    }
    // Interleave the M columns of each tile into output rows, then the epilogue. The
    // interleaved row reuses sbuf.
    let (tx, ty_n) = (wz.tx, s.oh.div_ceil(M));
    let row = &mut sbuf[..tx * M];
    for (k, gu) in (b0..b0 + tb / tx).enumerate() {
        let (n, ty) = (gu / ty_n, gu % ty_n);
        let (lo, _) = part.rows_of(n, s.oh);
        let res = part.residual(n, c);
        let plane = part.plane(n, c);
        for r in 0..M {
            let oy = ty * M + r;
            if oy >= s.oh {
                break;
            }
            interleave::<M>(&ybuf[r * M * ts + k * tx..], ts, row);
            let at = (oy - lo) * s.ow;
            finish(&mut plane[at..][..s.ow], &row[..s.ow], c, ep, res.map(|r| &r[at..]));
        }
    }
}
