//! Sparse 3-D convolution (`readi_plan::ops::SparseConv3d`, spconv's gather-GEMM-scatter),
//! the output sites of a strided one (`sparse_out_coords`) and `sparse_to_dense`.
//!
//! Coords arrive as f32 rows `(z, y, x)` (the runtime holds i64 tensors as f32); every run
//! checks them: integers inside the grid, the active rows a prefix, the rest `-1`, no site
//! twice. Per run and step, the conv hashes the active input sites (open addressing with
//! linear probing, a power-of-two table of at least twice the capacity, sized at bind
//! time) and builds its rulebook: for each active output row and kernel tap, the input
//! row it reads or none. Then, per block of [`BLOCK`] output rows and per tap, it gathers
//! the input rows the block reads into a `[m, Cin]` tile, multiplies it by that tap's
//! `[Cin, Cout]` slice of the weight with the runtime's panel GEMM (`panel.rs`: the
//! weight packed into panels once per run, in bound scratch; the `gemm` crate's
//! `sgemm` allocates its packing buffers on some calls), and adds the product rows into
//! their output rows. Blocks start at multiples of [`BLOCK`] whatever the thread
//! count and each output row takes its taps in order, so results are the same bits at
//! any number of threads.

use rayon::prelude::*;
use readi_plan::ops::{SparseConv3d, SparseOutCoords, SparseToDense, Window3, sparse_out_shape};

use super::panel::{self, PANEL};

/// Output rows per gather-GEMM-scatter block.
pub const BLOCK: usize = 64;

/// An empty slot of the hash table and a tap reading no active input.
const NONE: u32 = u32::MAX;

/// The sizes of a sparse step, from its checked shapes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Dims {
    /// Input rows (capacity) and channels.
    pub v_in: usize,
    pub cin: usize,
    /// Output rows (capacity) and channels (`sparse_out_coords`: 3).
    pub v_out: usize,
    pub cout: usize,
    pub taps: usize,
    pub grid_in: [usize; 3],
    pub grid_out: [usize; 3],
    pub window: Window3,
}

fn grid(s: [i64; 3], w: &Window3) -> Result<([usize; 3], [usize; 3]), String> {
    let out = sparse_out_shape(s, w).map_err(|e| e.message)?;
    let u = |a: [i64; 3]| a.map(|v| v as usize);
    Ok((u(s), u(out)))
}

fn taps(w: &Window3) -> usize {
    w.kernel.iter().map(|&k| k as usize).product()
}

fn two_d(x: &[usize], what: &str) -> Result<[usize; 2], String> {
    match *x {
        [a, b] => Ok([a, b]),
        _ => Err(format!("{what} of shape {x:?}, not [V, C]")),
    }
}

/// Checks a `sparse_conv3d` step's shapes; its sizes.
pub fn check_conv(op: &SparseConv3d, inputs: &[&[usize]], out: &[usize]) -> Result<Dims, String> {
    let (grid_in, grid_out) = grid(op.spatial_shape, &op.window)?;
    let [v_in, cin] = two_d(inputs[0], "features")?;
    let [vc, three] = two_d(inputs[1], "coords")?;
    let [v_out, three_o] = two_d(inputs[2], "out_coords")?;
    let taps = taps(&op.window);
    let [k0, k1, k2] = op.window.kernel.map(|k| k as usize);
    let cout = out.get(1).copied().unwrap_or(0);
    if vc != v_in || three != 3 || three_o != 3 || out != [v_out, cout] {
        return Err(format!("sparse conv of {:?}, {:?}, {:?} into {out:?}", inputs[0], inputs[1], inputs[2]));
    }
    if inputs[3] != [k0, k1, k2, cin, cout] {
        return Err(format!("sparse conv weight {:?}, it needs {:?}", inputs[3], [k0, k1, k2, cin, cout]));
    }
    if op.bias && inputs.get(4) != Some(&&[cout][..]) {
        return Err(format!("sparse conv bias {:?}, it needs [{cout}]", inputs.get(4)));
    }
    if cin == 0 || cout == 0 {
        return Err(format!("sparse conv of {cin} input and {cout} output channels"));
    }
    if v_in >= NONE as usize || v_out >= NONE as usize {
        return Err("sparse conv of 2^32 rows or more".into());
    }
    Ok(Dims { v_in, cin, v_out, cout, taps, grid_in, grid_out, window: op.window })
}

/// Checks a `sparse_out_coords` step's shapes; its sizes.
pub fn check_out_coords(op: &SparseOutCoords, inputs: &[&[usize]], out: &[usize]) -> Result<Dims, String> {
    let (grid_in, grid_out) = grid(op.spatial_shape, &op.window)?;
    let [v_in, three] = two_d(inputs[0], "coords")?;
    let [v_out, three_o] = two_d(out, "out_coords")?;
    if three != 3 || three_o != 3 || op.max_out.is_some_and(|m| m as usize != v_out) {
        return Err(format!("sparse_out_coords of {:?} into {out:?}", inputs[0]));
    }
    let taps = taps(&op.window);
    v_in.checked_mul(taps).filter(|&n| n < 1 << 40).ok_or("sparse_out_coords candidates overflow")?;
    Ok(Dims { v_in, cin: 3, v_out, cout: 3, taps, grid_in, grid_out, window: op.window })
}

/// Checks a `sparse_to_dense` step's shapes.
pub fn check_to_dense(op: &SparseToDense, inputs: &[&[usize]], out: &[usize]) -> Result<(), String> {
    let [v, c] = two_d(inputs[0], "features")?;
    let [s0, s1, s2] = op.spatial_shape.map(|d| d as usize);
    if inputs[1] != [v, 3] || out != [1, c, s0, s1, s2] {
        return Err(format!("sparse_to_dense of {:?}, {:?} into {out:?}", inputs[0], inputs[1]));
    }
    Ok(())
}

/// A sparse step's scratch, sized once (at bind time in a session).
#[derive(Debug, Default)]
pub struct Scratch {
    /// Hash table of the active input sites: linear index, row.
    keys: Vec<i64>,
    rows: Vec<u32>,
    /// `[v_out, taps]`: the input row each output row reads through each tap.
    rulebook: Vec<u32>,
    /// Per part (thread), a `[BLOCK, cin]` gather tile and a `[BLOCK, cout]` product.
    gather: Vec<f32>,
    product: Vec<f32>,
    /// The weight packed per tap for the panel GEMM, `taps · packed_len(cin, cout)`.
    packed: Vec<f32>,
    /// `sparse_out_coords`: the candidate output sites, `[v_in · taps]`.
    candidates: Vec<i64>,
    parts: usize,
}

impl Scratch {
    /// The table size for `v` sites: a power of two of at least `2v` (and 2).
    fn table_len(v: usize) -> usize {
        (2 * v.max(1)).next_power_of_two()
    }

    /// Bytes the scratch of a conv of these sizes takes on `threads` threads.
    pub fn conv_bytes(d: &Dims, threads: usize) -> Option<usize> {
        let t = Self::table_len(d.v_in).checked_mul(12)?;
        let r = d.v_out.checked_mul(d.taps)?.checked_mul(4)?;
        let g = threads.max(1).checked_mul(BLOCK)?.checked_mul(d.cin.checked_add(d.cout)?)?.checked_mul(4)?;
        let p = d.taps.checked_mul(d.cout.div_ceil(PANEL))?.checked_mul(PANEL)?.checked_mul(d.cin)?.checked_mul(4)?;
        t.checked_add(r)?.checked_add(g)?.checked_add(p)
    }

    /// Bytes the scratch of a `sparse_out_coords` of these sizes takes.
    pub fn out_coords_bytes(d: &Dims) -> Option<usize> {
        d.v_in.checked_mul(d.taps)?.checked_mul(8)
    }

    pub fn conv(d: &Dims, threads: usize) -> Scratch {
        let n = Self::table_len(d.v_in);
        let parts = threads.max(1);
        Scratch {
            keys: vec![-1; n],
            rows: vec![NONE; n],
            rulebook: vec![NONE; d.v_out * d.taps],
            gather: vec![0.0; parts * BLOCK * d.cin],
            product: vec![0.0; parts * BLOCK * d.cout],
            packed: vec![0.0; d.taps * panel::packed_len(d.cin, d.cout)],
            candidates: Vec::new(),
            parts,
        }
    }

    pub fn out_coords(d: &Dims) -> Scratch {
        Scratch { candidates: vec![0; d.v_in * d.taps], ..Scratch::default() }
    }
}

/// The number of active rows of `coords` (`[v, 3]` as f32) in a grid `g`, or why the
/// coords are refused.
pub fn active(coords: &[f32], g: [usize; 3], what: &str) -> Result<usize, String> {
    let mut n = None;
    for (r, c) in coords.chunks_exact(3).enumerate() {
        if c.iter().all(|&v| v == -1.0) {
            n.get_or_insert(r);
            continue;
        }
        if let Some(first) = n {
            return Err(format!(
                "{what} row {r} is active after inactive row {first}: the active sites must be a prefix of the rows"
            ));
        }
        let ok = c.iter().zip(g).all(|(&v, s)| v.fract() == 0.0 && v >= 0.0 && v < s as f32);
        if !ok {
            return Err(format!(
                "{what} row {r} is ({}, {}, {}), not a site of the grid {g:?} nor (-1, -1, -1)",
                c[0], c[1], c[2]
            ));
        }
    }
    Ok(n.unwrap_or(coords.len() / 3))
}

fn site(c: &[f32]) -> [i64; 3] {
    [c[0] as i64, c[1] as i64, c[2] as i64]
}

fn linear(s: [i64; 3], g: [usize; 3]) -> i64 {
    (s[0] * g[1] as i64 + s[1]) * g[2] as i64 + s[2]
}

/// A hash of a linear index into a table of `mask + 1` slots.
fn slot(key: i64, mask: usize) -> usize {
    (key as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15).rotate_right(29) as usize & mask
}

/// Fills the hash table with the first `n` sites of `coords`; a site twice is an error.
fn build_table(s: &mut Scratch, coords: &[f32], n: usize, g: [usize; 3]) -> Result<(), String> {
    s.keys.fill(-1);
    s.rows.fill(NONE);
    let mask = s.keys.len() - 1;
    for (r, c) in coords.chunks_exact(3).take(n).enumerate() {
        let key = linear(site(c), g);
        let mut h = slot(key, mask);
        while s.rows[h] != NONE {
            if s.keys[h] == key {
                return Err(format!(
                    "coords rows {} and {r} are the same site ({}, {}, {})",
                    s.rows[h], c[0], c[1], c[2]
                ));
            }
            h = (h + 1) & mask;
        }
        (s.keys[h], s.rows[h]) = (key, r as u32);
    }
    Ok(())
}

fn lookup(keys: &[i64], rows: &[u32], key: i64) -> u32 {
    let mask = keys.len() - 1;
    let mut h = slot(key, mask);
    while rows[h] != NONE {
        if keys[h] == key {
            return rows[h];
        }
        h = (h + 1) & mask;
    }
    NONE
}

/// The taps `(kz, ky, kx)` of a window, in weight order.
fn tap_offsets(w: &Window3) -> impl Iterator<Item = [i64; 3]> + '_ {
    let [k0, k1, k2] = w.kernel;
    (0..k0).flat_map(move |a| (0..k1).flat_map(move |b| (0..k2).map(move |c| [a, b, c])))
}

/// The sparse conv: `out` (`[v_out, cout]`) at the active rows of `out_coords`, zero at
/// the others. `weight` is `[kD, kH, kW, cin, cout]`.
#[allow(clippy::too_many_arguments)]
pub fn sparse_conv3d(
    d: &Dims,
    s: &mut Scratch,
    x: &[f32],
    coords: &[f32],
    out_coords: &[f32],
    weight: &[f32],
    bias: Option<&[f32]>,
    out: &mut [f32],
) -> Result<(), String> {
    let n_in = active(coords, d.grid_in, "coords")?;
    let n_out = active(out_coords, d.grid_out, "out_coords")?;
    build_table(s, coords, n_in, d.grid_in)?;
    let w = d.window;
    let (gi, taps) = (d.grid_in, d.taps);
    let (keys, rows) = (&s.keys, &s.rows);
    s.rulebook[..n_out * taps].par_chunks_mut(taps * BLOCK).enumerate().for_each(|(b, book)| {
        for (j, entry) in book.chunks_mut(taps).enumerate() {
            let r = b * BLOCK + j;
            let o = site(&out_coords[3 * r..3 * r + 3]);
            for (e, k) in entry.iter_mut().zip(tap_offsets(&w)) {
                let mut i = [0i64; 3];
                let mut inside = true;
                for a in 0..3 {
                    i[a] = o[a] * w.stride[a] - w.padding[a] + k[a] * w.dilation[a];
                    inside &= i[a] >= 0 && i[a] < gi[a] as i64;
                }
                *e = if inside { lookup(keys, rows, linear(i, gi)) } else { NONE };
            }
        }
    });
    let (cin, cout) = (d.cin, d.cout);
    out.fill(0.0);
    if let Some(b) = bias {
        out[..n_out * cout].chunks_exact_mut(cout).for_each(|row| row.copy_from_slice(b));
    }
    if n_out == 0 || cout == 0 {
        return Ok(());
    }
    // Each tap's `[cin, cout]` slice as `[ceil(cout / PANEL)][cin][PANEL]` panels.
    let plen = panel::packed_len(cin, cout);
    s.packed.par_chunks_mut(plen.max(1)).zip(weight.par_chunks(cin * cout)).for_each(|(dst, wt)| {
        for (p, pan) in dst.chunks_mut(cin * PANEL).enumerate() {
            for (i, row) in pan.chunks_mut(PANEL).enumerate() {
                for (c, v) in row.iter_mut().enumerate() {
                    let j = p * PANEL + c;
                    *v = if j < cout { wt[i * cout + j] } else { 0.0 };
                }
            }
        }
    });
    // Parts of whole blocks, one per thread at most, each with its own tiles.
    let blocks = n_out.div_ceil(BLOCK);
    let part_blocks = blocks.div_ceil(s.parts);
    let (book, packed) = (&s.rulebook, &s.packed);
    out[..n_out * cout]
        .par_chunks_mut(part_blocks * BLOCK * cout)
        .zip(s.gather.par_chunks_mut(BLOCK * cin.max(1)))
        .zip(s.product.par_chunks_mut(BLOCK * cout))
        .enumerate()
        .for_each(|(p, ((part, gather), product))| {
            for (bb, dst) in part.chunks_mut(BLOCK * cout).enumerate() {
                let first = (p * part_blocks + bb) * BLOCK;
                let len = dst.len() / cout;
                let mut at = [0u32; BLOCK];
                for t in 0..taps {
                    let mut m = 0;
                    for j in 0..len {
                        let src = book[(first + j) * taps + t];
                        if src != NONE {
                            let src = src as usize;
                            gather[m * cin..(m + 1) * cin].copy_from_slice(&x[src * cin..(src + 1) * cin]);
                            at[m] = j as u32;
                            m += 1;
                        }
                    }
                    if m == 0 {
                        continue;
                    }
                    let wt = &packed[t * plen..(t + 1) * plen];
                    panel::gemm(&gather[..m * cin], m, cin, wt, cout, &mut product[..m * cout]);
                    for (q, &j) in at[..m].iter().enumerate() {
                        let row = &mut dst[j as usize * cout..(j as usize + 1) * cout];
                        row.iter_mut().zip(&product[q * cout..(q + 1) * cout]).for_each(|(o, v)| *o += v);
                    }
                }
            }
        });
    Ok(())
}

/// The active outputs of a strided sparse conv of `coords`: every output site whose
/// window holds an active input, sorted by linear index, then `-1` rows. More than the
/// output's rows is an error.
pub fn sparse_out_coords(d: &Dims, s: &mut Scratch, coords: &[f32], out: &mut [f32]) -> Result<(), String> {
    let n_in = active(coords, d.grid_in, "coords")?;
    let (w, go) = (d.window, d.grid_out);
    let mut len = 0;
    for c in coords.chunks_exact(3).take(n_in) {
        let i = site(c);
        for k in tap_offsets(&w) {
            let mut o = [0i64; 3];
            let mut hit = true;
            for a in 0..3 {
                let num = i[a] + w.padding[a] - k[a] * w.dilation[a];
                hit &= num >= 0 && num % w.stride[a] == 0 && num / w.stride[a] < go[a] as i64;
                o[a] = num / w.stride[a].max(1);
            }
            if hit {
                s.candidates[len] = linear(o, go);
                len += 1;
            }
        }
    }
    let cand = &mut s.candidates[..len];
    cand.par_sort_unstable();
    let mut m = 0;
    for j in 0..cand.len() {
        if j == 0 || cand[j] != cand[j - 1] {
            cand[m] = cand[j];
            m += 1;
        }
    }
    if m > d.v_out {
        return Err(format!(
            "the sparse conv has {m} active output sites, more than its capacity {}: raise max_out",
            d.v_out
        ));
    }
    out.fill(-1.0);
    let (h, wd) = (go[1] as i64, go[2] as i64);
    for (row, &l) in out.chunks_exact_mut(3).zip(&cand[..m]) {
        row.copy_from_slice(&[(l / (h * wd)) as f32, (l / wd % h) as f32, (l % wd) as f32]);
    }
    Ok(())
}

/// spconv's `.dense()`: `out` `[1, c, D, H, W]`, each active row's features at its site.
pub fn sparse_to_dense(op: &SparseToDense, x: &[f32], coords: &[f32], out: &mut [f32]) -> Result<(), String> {
    let g = op.spatial_shape.map(|v| v as usize);
    let n = active(coords, g, "coords")?;
    let plane = g.iter().product::<usize>();
    let c = if coords.is_empty() { 0 } else { x.len() / (coords.len() / 3) };
    out.fill(0.0);
    for (r, s) in coords.chunks_exact(3).take(n).enumerate() {
        let l = linear(site(s), g) as usize;
        for ch in 0..c {
            out[ch * plane + l] = x[r * c + ch];
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::super::testutil::{assert_close, data};
    use super::*;

    /// The dense conv3d at site `o` of `out_coords`, inactive inputs zero: the reference.
    fn naive(d: &Dims, x: &[f32], coords: &[[i64; 3]], outs: &[[i64; 3]], w: &[f32]) -> Vec<f32> {
        let (cin, cout) = (d.cin, d.cout);
        let mut out = vec![0.0f32; d.v_out * cout];
        for (r, o) in outs.iter().enumerate() {
            for (t, k) in tap_offsets(&d.window).enumerate() {
                let i: Vec<i64> = (0..3)
                    .map(|a| o[a] * d.window.stride[a] - d.window.padding[a] + k[a] * d.window.dilation[a])
                    .collect();
                if let Some(src) = coords.iter().position(|c| c[..] == i[..]) {
                    for co in 0..cout {
                        for ci in 0..cin {
                            out[r * cout + co] += x[src * cin + ci] * w[(t * cin + ci) * cout + co];
                        }
                    }
                }
            }
        }
        out
    }

    fn flat(c: &[[i64; 3]], cap: usize) -> Vec<f32> {
        let mut v: Vec<f32> = c.iter().flat_map(|s| s.map(|x| x as f32)).collect();
        v.resize(cap * 3, -1.0);
        v
    }

    fn sites(n: usize, g: [usize; 3], seed: u64) -> Vec<[i64; 3]> {
        let mut all: Vec<[i64; 3]> = Vec::new();
        let mut h = seed;
        while all.len() < n {
            h = h.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            let s = [(h >> 33) as usize % g[0], (h >> 41) as usize % g[1], (h >> 49) as usize % g[2]].map(|v| v as i64);
            if !all.contains(&s) {
                all.push(s);
            }
        }
        all
    }

    #[test]
    fn strided_and_subm_match_the_naive_conv_at_any_thread_count() {
        let g = [5usize, 9, 7];
        let spatial = g.map(|v| v as i64);
        let cases = [
            (Window3 { kernel: [3; 3], stride: [1; 3], padding: [1; 3], dilation: [1; 3] }, true),
            (Window3 { kernel: [3; 3], stride: [2; 3], padding: [1; 3], dilation: [1; 3] }, false),
            (Window3 { kernel: [3, 1, 1], stride: [2, 1, 1], padding: [0; 3], dilation: [1; 3] }, false),
        ];
        for (case, (window, subm)) in cases.into_iter().enumerate() {
            let (cap, n, cin, cout) = (150, 130, 5, 7);
            let coords = sites(n, g, case as u64 + 1);
            let cf = flat(&coords, cap);
            let oc_op = SparseOutCoords { spatial_shape: spatial, window, max_out: Some(400) };
            let od = check_out_coords(&oc_op, &[&[cap, 3]], &[400, 3]).expect("shapes");
            let mut ocs = vec![0.0; 400 * 3];
            if subm {
                ocs = flat(&coords, 400);
            } else {
                sparse_out_coords(&od, &mut Scratch::out_coords(&od), &cf, &mut ocs).expect("fits");
            }
            let n_out = active(&ocs, od.grid_out, "out").expect("valid");
            let outs: Vec<[i64; 3]> = ocs.chunks(3).take(n_out).map(site).collect();
            if !subm {
                // The dilation: every output whose window holds an input, each once, sorted.
                let mut want = Vec::new();
                for z in 0..od.grid_out[0] as i64 {
                    for y in 0..od.grid_out[1] as i64 {
                        for x in 0..od.grid_out[2] as i64 {
                            let o = [z, y, x];
                            let hit = tap_offsets(&window).any(|k| {
                                let i: Vec<i64> =
                                    (0..3).map(|a| o[a] * window.stride[a] - window.padding[a] + k[a]).collect();
                                coords.iter().any(|c| c[..] == i[..])
                            });
                            if hit {
                                want.push(o);
                            }
                        }
                    }
                }
                assert_eq!(outs, want, "case {case}");
            }
            let op = SparseConv3d { spatial_shape: spatial, window, subm, bias: false };
            let k = window.kernel.map(|v| v as usize);
            let wshape = [k[0], k[1], k[2], cin, cout];
            let d = check_conv(&op, &[&[cap, cin], &[cap, 3], &[400, 3], &wshape], &[400, cout]).expect("shapes");
            let x = data(cap * cin, 3);
            let w = data(wshape.iter().product(), 4);
            let want = naive(&d, &x, &coords, &outs, &w);
            let mut bits = Vec::new();
            for threads in [1, 2, 3] {
                let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().expect("pool");
                let mut out = vec![f32::NAN; 400 * cout];
                let mut s = Scratch::conv(&d, threads);
                pool.install(|| sparse_conv3d(&d, &mut s, &x, &cf, &ocs, &w, None, &mut out)).expect("runs");
                assert_close(&out, &want, 1e-5);
                bits.push(out.iter().map(|v| v.to_bits()).collect::<Vec<_>>());
            }
            assert!(bits.windows(2).all(|b| b[0] == b[1]), "case {case}: bits differ across thread counts");
        }
    }

    #[test]
    fn bad_coords_are_refused() {
        let g = [4, 4, 4];
        assert_eq!(active(&flat(&[[0, 1, 2]], 3), g, "coords"), Ok(1));
        assert_eq!(active(&[], g, "coords"), Ok(0));
        let mut c = flat(&[[0, 1, 2]], 3);
        c[6..9].copy_from_slice(&[1.0, 1.0, 1.0]);
        assert!(active(&c, g, "coords").expect_err("hole").contains("prefix"));
        assert!(active(&flat(&[[0, 4, 0]], 1), g, "coords").expect_err("out").contains("not a site"));
        assert!(active(&[0.5, 0.0, 0.0], g, "coords").is_err());
        let op = SparseConv3d {
            spatial_shape: [4, 4, 4],
            window: Window3 { kernel: [1; 3], stride: [1; 3], padding: [0; 3], dilation: [1; 3] },
            subm: true,
            bias: false,
        };
        let d = check_conv(&op, &[&[2, 1], &[2, 3], &[2, 3], &[1, 1, 1, 1, 1]], &[2, 1]).expect("shapes");
        let twice = flat(&[[1, 1, 1], [1, 1, 1]], 2);
        let mut out = [0.0; 2];
        let e = sparse_conv3d(&d, &mut Scratch::conv(&d, 1), &[1.0, 2.0], &twice, &twice, &[1.0], None, &mut out);
        assert!(e.expect_err("duplicate").contains("same site"));
        let oc = SparseOutCoords {
            spatial_shape: [4, 4, 4],
            window: Window3 { kernel: [3; 3], ..d.window },
            max_out: Some(2),
        };
        let od = check_out_coords(&oc, &[&[2, 3]], &[2, 3]).expect("shapes");
        let e = sparse_out_coords(&od, &mut Scratch::out_coords(&od), &flat(&[[1, 1, 1]], 2), &mut [0.0; 6]);
        assert!(e.expect_err("over").contains("raise max_out"));
    }
}
