//! Data movement without arithmetic, row-major: `pad` (constant, reflect, replicate),
//! `roll`, `slice` (strided, with axes removed by an index) and `expand` (a broadcast
//! copy).
//!
//! Each kernel walks the output a last-axis row at a time and copies whole runs with
//! `copy_from_slice` (a memcpy) wherever the source is contiguous: a padded row is a fill,
//! one run and a fill; a rolled row two runs; a slice whose last axes are whole or
//! unit-step one run per outer index. Only a strided last axis is gathered element by
//! element.

use readi_plan::ops::{Pad, PadMode, Resolved, Roll, Slice};

/// Row-major strides of `shape`.
fn strides(shape: &[usize]) -> Vec<usize> {
    let mut s = vec![1; shape.len()];
    for i in (0..shape.len().saturating_sub(1)).rev() {
        s[i] = s[i + 1] * shape[i + 1];
    }
    s
}

/// Where output index `o` along a padded axis reads, `None` for the constant.
#[inline]
fn pad_source(o: i64, before: i64, d: i64, mode: PadMode) -> Option<usize> {
    let i = o - before;
    if (0..d).contains(&i) {
        return Some(i as usize);
    }
    match mode {
        PadMode::Constant => None,
        PadMode::Replicate => Some(i.clamp(0, d - 1) as usize),
        // |i| < d by the shape rule, so one reflection lands inside.
        PadMode::Reflect => Some(if i < 0 { -i } else { 2 * (d - 1) - i } as usize),
    }
}

/// Checks `out` is the shape `pad` gives `x`.
pub fn check_pad(p: &Pad, x: &[usize], out: &[usize]) -> Result<(), String> {
    let want = pad_shape(p, x)?;
    if want != out {
        return Err(format!("pad of {x:?} gives {want:?}, the plan says {out:?}"));
    }
    Ok(())
}

fn pad_shape(p: &Pad, x: &[usize]) -> Result<Vec<usize>, String> {
    if !p.pads.len().is_multiple_of(2) || p.pads.len() > 2 * x.len() {
        return Err(format!("pad {:?} does not fit a rank-{} input", p.pads, x.len()));
    }
    x.iter()
        .zip(p.per_axis(x.len()))
        .map(|(&d, (l, r))| {
            let di = d as i64;
            let bad = match p.mode {
                PadMode::Reflect => (l, r) != (0, 0) && (l >= di || r >= di),
                PadMode::Replicate => (l, r) != (0, 0) && d == 0,
                PadMode::Constant => false,
            };
            let o = di + l + r;
            if bad || o < 0 {
                return Err(format!("pad ({l}, {r}) in mode {} does not fit an axis of {d}", p.mode.name()));
            }
            Ok(o as usize)
        })
        .collect()
}

/// `torch.nn.functional.pad`: `x` (shape `xs`) padded as `p` says into `out`.
pub fn pad(p: &Pad, x: &[f32], xs: &[usize], out: &mut [f32]) {
    let os = pad_shape(p, xs).expect("pad: shapes checked at bind time");
    assert_eq!(x.len(), xs.iter().product::<usize>(), "pad: x does not match its shape");
    assert_eq!(out.len(), os.iter().product::<usize>(), "pad: out does not match its shape");
    if out.is_empty() {
        return;
    }
    let value = p.value as f32;
    if xs.is_empty() {
        out[0] = x[0];
        return;
    }
    let r = xs.len();
    let amounts = p.per_axis(r);
    let st = strides(xs);
    let (w, ow) = (xs[r - 1], os[r - 1]);
    let (lw, _) = amounts[r - 1];
    // Output columns `[lo, hi)` read input columns `lo - lw ..`: one run.
    let lo = lw.clamp(0, ow as i64) as usize;
    let hi = (lw + w as i64).clamp(0, ow as i64) as usize;
    let mut idx = vec![0usize; r - 1];
    for row in out.chunks_mut(ow) {
        // The input row this output row reads, or none (constant border).
        let mut base = Some(0usize);
        for a in 0..r - 1 {
            let src = pad_source(idx[a] as i64, amounts[a].0, xs[a] as i64, p.mode);
            base = match (base, src) {
                (Some(b), Some(s)) => Some(b + s * st[a]),
                _ => None,
            };
        }
        match base {
            None => row.fill(value),
            Some(b) => {
                let src = &x[b..b + w];
                if hi > lo {
                    let s0 = (lo as i64 - lw) as usize;
                    row[lo..hi].copy_from_slice(&src[s0..s0 + (hi - lo)]);
                }
                for o in (0..lo).chain(hi..ow) {
                    row[o] = match pad_source(o as i64, lw, w as i64, p.mode) {
                        Some(s) => src[s],
                        None => value,
                    };
                }
            }
        }
        for a in (0..r - 1).rev() {
            idx[a] += 1;
            if idx[a] < os[a] {
                break;
            }
            idx[a] = 0;
        }
    }
}

/// Checks a roll: same length in and out, axes in range.
pub fn check_roll(p: &Roll, x: &[usize], out: &[usize]) -> Result<(), String> {
    if x != out {
        return Err(format!("roll of {x:?} keeps the shape, the plan says {out:?}"));
    }
    if p.axes.iter().any(|&a| a >= x.len()) || (p.axes.is_empty() && p.shifts.len() != 1) {
        return Err(format!("roll over {:?} does not fit a rank-{} input", p.axes, x.len()));
    }
    if !p.axes.is_empty() && p.axes.len() != p.shifts.len() {
        return Err("roll needs one shift per dim".into());
    }
    Ok(())
}

/// `s` modulo `d`, in `[0, d)`.
fn wrap(s: i64, d: usize) -> usize {
    if d == 0 { 0 } else { s.rem_euclid(d as i64) as usize }
}

/// `torch.roll`: output index `i` along a rolled axis reads input `i - shift` modulo the
/// size; without axes, the flattened tensor is rolled.
pub fn roll(p: &Roll, x: &[f32], xs: &[usize], out: &mut [f32]) {
    assert_eq!(x.len(), out.len(), "roll: out and x differ in length");
    if x.is_empty() {
        return;
    }
    if p.axes.is_empty() {
        let n = x.len();
        let s = wrap(p.shifts[0], n);
        out[s..].copy_from_slice(&x[..n - s]);
        out[..s].copy_from_slice(&x[n - s..]);
        return;
    }
    let r = xs.len();
    let mut shift = vec![0usize; r];
    for (&a, &s) in p.axes.iter().zip(&p.shifts) {
        shift[a] = (shift[a] + wrap(s, xs[a])) % xs[a].max(1);
    }
    let st = strides(xs);
    let w = xs[r - 1];
    let sw = shift[r - 1];
    let mut idx = vec![0usize; r - 1];
    for row in out.chunks_mut(w) {
        let mut b = 0;
        for a in 0..r - 1 {
            b += ((idx[a] + xs[a] - shift[a]) % xs[a]) * st[a];
        }
        let src = &x[b..b + w];
        row[sw..].copy_from_slice(&src[..w - sw]);
        row[..sw].copy_from_slice(&src[w - sw..]);
        for a in (0..r - 1).rev() {
            idx[a] += 1;
            if idx[a] < xs[a] {
                break;
            }
            idx[a] = 0;
        }
    }
}

/// Checks `out` is what `s` leaves of `x`.
pub fn check_slice(s: &Slice, x: &[usize], out: &[usize]) -> Result<(), String> {
    let want: Vec<usize> = s.resolve(x)?.iter().filter(|r| r.keep).map(|r| r.len).collect();
    if want != out {
        return Err(format!("slice of {x:?} gives {want:?}, the plan says {out:?}"));
    }
    Ok(())
}

/// `x[...]`: the elements `s` selects, in order, into `out`.
pub fn slice(s: &Slice, x: &[f32], xs: &[usize], out: &mut [f32]) {
    let rs = s.resolve(xs).expect("slice: shapes checked at bind time");
    assert_eq!(x.len(), xs.iter().product::<usize>(), "slice: x does not match its shape");
    assert_eq!(out.len(), rs.iter().map(|r| r.len).product::<usize>(), "slice: out length");
    if out.is_empty() {
        return;
    }
    let st = strides(xs);
    // Axes `j..` read one contiguous run per outer index: trailing axes taken whole, and
    // the unit-step axis before them.
    let r = xs.len();
    let mut j = r;
    while j > 0 && rs[j - 1].start == 0 && rs[j - 1].len == xs[j - 1] && rs[j - 1].step == 1 {
        j -= 1;
    }
    if j > 0 && rs[j - 1].step == 1 {
        j -= 1;
    }
    if j < r {
        let run: usize = rs[j..].iter().map(|r| r.len).product();
        let offset = rs[j].start * st[j];
        let mut idx = vec![0usize; j];
        for o in out.chunks_mut(run) {
            let b: usize = (0..j).map(|a| (rs[a].start + idx[a] * rs[a].step) * st[a]).sum::<usize>() + offset;
            o.copy_from_slice(&x[b..b + run]);
            odometer(&mut idx, &rs[..j]);
        }
    } else {
        // A strided last axis: each output row gathers from one input row.
        let last = rs[r - 1];
        let mut idx = vec![0usize; r - 1];
        for o in out.chunks_mut(last.len) {
            let b: usize = (0..r - 1).map(|a| (rs[a].start + idx[a] * rs[a].step) * st[a]).sum::<usize>() + last.start;
            for (k, v) in o.iter_mut().enumerate() {
                *v = x[b + k * last.step];
            }
            odometer(&mut idx, &rs[..r - 1]);
        }
    }
}

/// Checks `out` is a broadcast of `x` (trailing axes aligned, each 1 or equal).
pub fn check_expand(x: &[usize], out: &[usize]) -> Result<(), String> {
    let ok = out.len() >= x.len() && x.iter().zip(&out[out.len() - x.len()..]).all(|(&d, &o)| d == o || d == 1);
    if !ok {
        return Err(format!("cannot expand {x:?} to {out:?}"));
    }
    Ok(())
}

/// `x.expand(out_shape)`: each output last-axis row is a copy of its source row, or its
/// source element repeated when the last axis is broadcast.
pub fn expand(x: &[f32], xs: &[usize], out: &mut [f32], os: &[usize]) {
    assert_eq!(out.len(), os.iter().product::<usize>(), "expand: out does not match its shape");
    if out.is_empty() {
        return;
    }
    let r = os.len();
    // The input's shape and strides aligned to the output's axes; stride 0 repeats.
    let mut xd = vec![1usize; r];
    xd[r - xs.len()..].copy_from_slice(xs);
    let st = strides(&xd);
    let st: Vec<usize> = st.iter().zip(&xd).map(|(&s, &d)| if d == 1 { 0 } else { s }).collect();
    let w = os[r - 1];
    let mut idx = vec![0usize; r - 1];
    for row in out.chunks_mut(w) {
        let b: usize = (0..r - 1).map(|a| idx[a] * st[a]).sum();
        if xd[r - 1] == 1 {
            row.fill(x[b]);
        } else {
            row.copy_from_slice(&x[b..b + w]);
        }
        for a in (0..r - 1).rev() {
            idx[a] += 1;
            if idx[a] < os[a] {
                break;
            }
            idx[a] = 0;
        }
    }
}

/// Advances a row-major multi-index over the resolved lengths.
fn odometer(idx: &mut [usize], rs: &[Resolved]) {
    for a in (0..idx.len()).rev() {
        idx[a] += 1;
        if idx[a] < rs[a].len {
            return;
        }
        idx[a] = 0;
    }
}

#[cfg(test)]
mod tests {
    use readi_plan::ops::SliceAxis;

    use super::*;

    fn iota(n: usize) -> Vec<f32> {
        (0..n).map(|i| i as f32 + 1.0).collect()
    }

    fn unravel(mut i: usize, shape: &[usize]) -> Vec<usize> {
        let mut idx = vec![0; shape.len()];
        for a in (0..shape.len()).rev() {
            idx[a] = i % shape[a];
            i /= shape[a];
        }
        idx
    }

    fn ravel(idx: &[usize], shape: &[usize]) -> usize {
        idx.iter().zip(shape).fold(0, |acc, (&i, &d)| acc * d + i)
    }

    /// Element by element, the definition: every output index maps back per axis.
    fn naive_pad(p: &Pad, x: &[f32], xs: &[usize]) -> (Vec<f32>, Vec<usize>) {
        let am = p.per_axis(xs.len());
        let os: Vec<usize> = xs.iter().zip(&am).map(|(&d, (l, r))| (d as i64 + l + r) as usize).collect();
        let n = os.iter().product();
        let out = (0..n)
            .map(|o| {
                let oi = unravel(o, &os);
                let mut src = Vec::new();
                for a in 0..xs.len() {
                    let (i, d) = (oi[a] as i64 - am[a].0, xs[a] as i64);
                    let s = match p.mode {
                        _ if (0..d).contains(&i) => i,
                        PadMode::Constant => return p.value as f32,
                        PadMode::Replicate => i.clamp(0, d - 1),
                        PadMode::Reflect if i < 0 => -i,
                        PadMode::Reflect => 2 * (d - 1) - i,
                    };
                    src.push(s as usize);
                }
                x[ravel(&src, xs)]
            })
            .collect();
        (out, os)
    }

    #[test]
    fn pad_matches_the_definition() {
        let shapes: &[&[usize]] = &[&[5], &[3, 4], &[2, 3, 5], &[1, 2, 3, 7], &[2, 1, 1]];
        let pads: &[&[i64]] = &[&[1, 2], &[0, 3, 2, 0], &[-1, 2], &[2, -1, -1, 1], &[0, 0, 1, 1, 1, 0], &[]];
        let mut ran = 0;
        for xs in shapes {
            let x = iota(xs.iter().product());
            for pads in pads {
                for mode in [PadMode::Constant, PadMode::Reflect, PadMode::Replicate] {
                    let p = Pad { pads: pads.to_vec(), mode, value: -0.5 };
                    let Ok(os) = pad_shape(&p, xs) else { continue };
                    let (want, wos) = naive_pad(&p, &x, xs);
                    assert_eq!(os, wos);
                    let mut got = vec![f32::NAN; want.len()];
                    pad(&p, &x, xs, &mut got);
                    assert_eq!(got, want, "{xs:?} {pads:?} {mode:?}");
                    ran += 1;
                }
            }
        }
        assert!(ran > 50, "{ran}");
    }

    #[test]
    fn pad_by_hand() {
        // torch.nn.functional.pad(torch.tensor([[1., 2., 3.]]), (2, 1), mode=m)
        let x = [1.0, 2.0, 3.0];
        let go = |mode| {
            let mut o = vec![0.0; 6];
            pad(&Pad { pads: vec![2, 1], mode, value: 9.0 }, &x, &[1, 3], &mut o);
            o
        };
        assert_eq!(go(PadMode::Constant), [9.0, 9.0, 1.0, 2.0, 3.0, 9.0]);
        assert_eq!(go(PadMode::Reflect), [3.0, 2.0, 1.0, 2.0, 3.0, 2.0]);
        assert_eq!(go(PadMode::Replicate), [1.0, 1.0, 1.0, 2.0, 3.0, 3.0]);
        assert!(pad_shape(&Pad { pads: vec![3, 0], mode: PadMode::Reflect, value: 0.0 }, &[1, 3]).is_err());
    }

    fn naive_roll(p: &Roll, x: &[f32], xs: &[usize]) -> Vec<f32> {
        if p.axes.is_empty() {
            let n = x.len() as i64;
            return (0..n).map(|i| x[(i - p.shifts[0]).rem_euclid(n) as usize]).collect();
        }
        (0..x.len())
            .map(|o| {
                let mut i = unravel(o, xs);
                for (&a, &s) in p.axes.iter().zip(&p.shifts) {
                    i[a] = (i[a] as i64 - s).rem_euclid(xs[a] as i64) as usize;
                }
                x[ravel(&i, xs)]
            })
            .collect()
    }

    #[test]
    fn roll_matches_the_definition() {
        let cases: &[(&[usize], &[i64], &[usize])] = &[
            (&[7], &[3], &[0]),
            (&[7], &[-10], &[]),
            (&[2, 3, 5], &[1, -2], &[0, 2]),
            (&[2, 3, 5], &[4], &[1]),
            (&[2, 3, 5], &[1, 1], &[2, 2]),
            (&[3, 1, 4], &[17], &[]),
            (&[3, 1, 4], &[-1, 5, 0], &[0, 1, 2]),
        ];
        for (xs, shifts, axes) in cases {
            let p = Roll { shifts: shifts.to_vec(), axes: axes.to_vec() };
            check_roll(&p, xs, xs).expect("valid");
            let x = iota(xs.iter().product());
            let mut got = vec![0.0; x.len()];
            roll(&p, &x, xs, &mut got);
            assert_eq!(got, naive_roll(&p, &x, xs), "{xs:?} {shifts:?} {axes:?}");
        }
        // torch.roll(torch.arange(1., 6.), 2) = [4, 5, 1, 2, 3]
        let mut o = vec![0.0; 5];
        roll(&Roll { shifts: vec![2], axes: vec![] }, &iota(5), &[5], &mut o);
        assert_eq!(o, [4.0, 5.0, 1.0, 2.0, 3.0]);
    }

    #[test]
    fn expand_matches_the_definition() {
        let cases: &[(&[usize], &[usize])] =
            &[(&[3, 1], &[2, 3, 4]), (&[1, 4], &[3, 4]), (&[2, 1, 3], &[2, 5, 3]), (&[1], &[7]), (&[2, 3], &[2, 3])];
        for (xs, os) in cases {
            check_expand(xs, os).expect("valid");
            let x = iota(xs.iter().product());
            let n = os.iter().product();
            let lead = os.len() - xs.len();
            let want: Vec<f32> = (0..n)
                .map(|o| {
                    let i = unravel(o, os);
                    let src: Vec<usize> =
                        xs.iter().enumerate().map(|(a, &d)| if d == 1 { 0 } else { i[lead + a] }).collect();
                    x[ravel(&src, xs)]
                })
                .collect();
            let mut got = vec![f32::NAN; n];
            expand(&x, xs, &mut got, os);
            assert_eq!(got, want, "{xs:?} -> {os:?}");
        }
        assert!(check_expand(&[2, 4], &[3, 4]).is_err());
        assert!(check_expand(&[1, 4], &[4]).is_err());
    }

    fn naive_slice(s: &Slice, x: &[f32], xs: &[usize]) -> Vec<f32> {
        let rs = s.resolve(xs).expect("resolves");
        let lens: Vec<usize> = rs.iter().map(|r| r.len).collect();
        (0..lens.iter().product())
            .map(|o| {
                let i = unravel(o, &lens);
                let src: Vec<usize> = i.iter().zip(&rs).map(|(&k, r)| r.start + k * r.step).collect();
                x[ravel(&src, xs)]
            })
            .collect()
    }

    fn rg(start: Option<i64>, stop: Option<i64>, step: i64) -> SliceAxis {
        SliceAxis::Range { start, stop, step }
    }

    #[test]
    fn slice_matches_the_definition() {
        let full = SliceAxis::FULL;
        let cases: Vec<(Vec<usize>, Vec<SliceAxis>)> = vec![
            (vec![10], vec![rg(Some(2), Some(-1), 3)]),
            (vec![10], vec![SliceAxis::Index(-1)]),
            (vec![3, 7], vec![full, rg(None, None, 2)]),
            (vec![3, 7], vec![rg(Some(1), None, 1), full]),
            (vec![3, 7], vec![SliceAxis::Index(1), rg(Some(-4), Some(100), 1)]),
            (vec![2, 3, 5], vec![full, rg(Some(0), Some(2), 1), full]),
            (vec![2, 3, 5], vec![full, SliceAxis::Index(-2), rg(None, None, 4)]),
            (vec![2, 3, 5], vec![rg(None, None, 2), full, SliceAxis::Index(0)]),
            (vec![2, 3, 5], vec![full, rg(Some(5), None, 1), full]),
            (vec![4, 1, 3, 6], vec![rg(Some(1), Some(3), 1), full, rg(None, None, 2), rg(Some(1), Some(5), 1)]),
        ];
        for (xs, axes) in cases {
            let s = Slice { axes };
            let x = iota(xs.iter().product());
            let want = naive_slice(&s, &x, &xs);
            let os: Vec<usize> = s.resolve(&xs).expect("ok").iter().filter(|r| r.keep).map(|r| r.len).collect();
            check_slice(&s, &xs, &os).expect("valid");
            let mut got = vec![f32::NAN; want.len()];
            slice(&s, &x, &xs, &mut got);
            assert_eq!(got, want, "{xs:?} {:?}", s.axes);
        }
        let s = Slice { axes: vec![SliceAxis::Index(3)] };
        assert!(check_slice(&s, &[3], &[]).is_err());
        assert!(check_slice(&Slice { axes: vec![full] }, &[3], &[2]).is_err());
    }
}
