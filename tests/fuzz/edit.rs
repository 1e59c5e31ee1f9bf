//! Edits of specs: deleted ranges, inserted tokens, duplicated and swapped lines, replaced
//! numbers and words.

use super::*;

#[derive(Clone, Debug)]
pub(super) enum Edit {
    Delete {
        at: usize,
        len: usize,
    },
    Insert {
        at: usize,
        token: &'static str,
    },
    DuplicateLine {
        line: usize,
    },
    SwapLines {
        a: usize,
        b: usize,
    },
    ReplaceNumber {
        nth: usize,
        with: &'static str,
    },
    /// The `nth` word of [`WORDS`] becomes the `pick`-th word of its group.
    ReplaceWord {
        nth: usize,
        pick: usize,
    },
}

pub(super) fn edit() -> impl Strategy<Value = Edit> {
    prop_oneof![
        (any::<usize>(), 1usize..40).prop_map(|(at, len)| Edit::Delete { at, len }),
        (any::<usize>(), prop::sample::select(TOKENS)).prop_map(|(at, token)| Edit::Insert { at, token }),
        any::<usize>().prop_map(|line| Edit::DuplicateLine { line }),
        (any::<usize>(), any::<usize>()).prop_map(|(a, b)| Edit::SwapLines { a, b }),
        (any::<usize>(), prop::sample::select(TOKENS)).prop_map(|(nth, with)| Edit::ReplaceNumber { nth, with }),
        (any::<usize>(), any::<usize>()).prop_map(|(nth, pick)| Edit::ReplaceWord { nth, pick }),
        (any::<usize>(), prop::sample::select(HOSTILE_NUMBERS))
            .prop_map(|(nth, with)| Edit::ReplaceNumber { nth, with }),
    ]
}

/// Numbers a hostile user would try (issue 10): sizes over the activation limit or that
/// overflow, a port count past 16 bits, infinite and negative results. Front end only:
/// a spec that checks with them could be gigabytes at batch 1.
pub(super) const HOSTILE_NUMBERS: &[&str] =
    &["65536", "65537", "4294967296", "99999999999", "9223372036854775807", "-1", "1e300", "0.0", "** -1"];

/// Sizes and factors an edit may put in place of a number and still often have a spec
/// that checks.
pub(super) const NUMBERS: &[&str] = &["0", "1", "2", "3", "4", "5", "8", "16", "0.5", "2.0"];

/// Words an edit may swap for another of their group: ops that take and give the same
/// kinds of tensors, arguments that take the same values.
pub(super) const WORDS: &[&[&str]] = &[
    &["relu", "sigmoid", "tanh", "silu", "gelu"],
    &["maxpool", "avgpool"],
    &["batchnorm", "layernorm"],
    &["stride", "padding", "dilation"],
    &["true", "false"],
    &["x", "y"],
];

/// Edits that keep the text a spec, and often one that checks: for the back end, which
/// sees only the specs that check.
pub(super) fn mild_edit() -> impl Strategy<Value = Edit> {
    prop_oneof![
        3 => (any::<usize>(), prop::sample::select(NUMBERS)).prop_map(|(nth, with)| Edit::ReplaceNumber { nth, with }),
        3 => (any::<usize>(), any::<usize>()).prop_map(|(nth, pick)| Edit::ReplaceWord { nth, pick }),
        1 => (any::<usize>(), any::<usize>()).prop_map(|(a, b)| Edit::SwapLines { a, b }),
    ]
}

/// Applies an edit at char boundaries.
pub(super) fn apply(src: &str, e: &Edit) -> String {
    let boundary = |at: usize| {
        let mut i = at % (src.len() + 1);
        while !src.is_char_boundary(i) {
            i -= 1;
        }
        i
    };
    match e {
        Edit::Delete { at, len } => {
            let a = boundary(*at);
            let b = boundary(a + len);
            format!("{}{}", &src[..a], &src[b.max(a)..])
        }
        Edit::Insert { at, token } => {
            let a = boundary(*at);
            format!("{} {token} {}", &src[..a], &src[a..])
        }
        Edit::DuplicateLine { line } => {
            let mut lines: Vec<&str> = src.lines().collect();
            if !lines.is_empty() {
                let i = line % lines.len();
                lines.insert(i, lines[i]);
            }
            lines.join("\n")
        }
        Edit::SwapLines { a, b } => {
            let mut lines: Vec<&str> = src.lines().collect();
            if !lines.is_empty() {
                let (i, j) = (a % lines.len(), b % lines.len());
                lines.swap(i, j);
            }
            lines.join("\n")
        }
        Edit::ReplaceNumber { nth, with } => {
            let starts: Vec<usize> = src
                .char_indices()
                .filter(|&(i, c)| c.is_ascii_digit() && !src[..i].ends_with(|p: char| p.is_alphanumeric() || p == '_'))
                .map(|(i, _)| i)
                .collect();
            if starts.is_empty() {
                return src.to_string();
            }
            let a = starts[nth % starts.len()];
            let b = src[a..].find(|c: char| !(c.is_ascii_digit() || c == '.')).map_or(src.len(), |k| a + k);
            format!("{}{with}{}", &src[..a], &src[b..])
        }
        Edit::ReplaceWord { nth, pick } => {
            let word = |c: char| c.is_ascii_alphanumeric() || c == '_';
            let mut found = Vec::new();
            let mut i = 0;
            while let Some(k) = src[i..].find(|c: char| c.is_ascii_alphabetic() || c == '_') {
                let a = i + k;
                let b = src[a..].find(|c: char| !word(c)).map_or(src.len(), |k| a + k);
                if let Some(group) = WORDS.iter().find(|g| g.contains(&&src[a..b]))
                    && !src[..a].ends_with(word)
                {
                    found.push((a, b, group[pick % group.len()]));
                }
                i = b;
            }
            match found.get(nth % found.len().max(1)) {
                Some(&(a, b, with)) => format!("{}{with}{}", &src[..a], &src[b..]),
                None => src.to_string(),
            }
        }
    }
}
