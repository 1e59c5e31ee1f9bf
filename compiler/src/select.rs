//! Path patterns of adaptation selectors, matched against dotted node paths.
//!
//! A pattern is a list of segments. A segment matches one path segment: `*` matches any
//! run of characters within it, `{a,b}` either alternative (`bn{1,2}`, `{q,k,v}`). The
//! segment `**` matches any number of path segments, including none. A pattern *selects*
//! a path when it matches the whole path or any prefix of it: selecting a scope selects
//! everything under it (`head` and `head.*` both select `head.cls.0.weight`'s layer).

use readi_grammar::ast::{Pattern, PatternSeg};

/// Whether `pattern` matches the whole of `path` (already split at dots).
pub fn matches(pattern: &[PatternSeg], path: &[&str]) -> bool {
    match pattern.split_first() {
        None => path.is_empty(),
        Some((PatternSeg::AnyDepth, rest)) => (0..=path.len()).any(|k| matches(rest, &path[k..])),
        Some((PatternSeg::Word(w), rest)) => match path.split_first() {
            Some((seg, tail)) => word_matches(w, seg) && matches(rest, tail),
            None => false,
        },
    }
}

/// Whether `pattern` matches `path` or one of its prefixes.
pub fn selects(pattern: &Pattern, path: &str) -> bool {
    let segs: Vec<&str> = if path.is_empty() { Vec::new() } else { path.split('.').collect() };
    (1..=segs.len()).any(|k| matches(&pattern.segments, &segs[..k]))
}

/// Whether `pattern` matches exactly `path`.
pub fn matches_exactly(pattern: &Pattern, path: &str) -> bool {
    let segs: Vec<&str> = if path.is_empty() { Vec::new() } else { path.split('.').collect() };
    matches(&pattern.segments, &segs)
}

/// Whether one segment glob (with `*` and `{a,b}`) matches one path segment.
pub fn word_matches(word: &str, seg: &str) -> bool {
    expand_alternatives(word).iter().any(|g| glob(g.as_bytes(), seg.as_bytes()))
}

/// `bn{1,2}x` to `["bn1x", "bn2x"]`; nested braces are not part of the syntax.
fn expand_alternatives(word: &str) -> Vec<String> {
    let Some(open) = word.find('{') else { return vec![word.to_string()] };
    let Some(close) = word[open..].find('}').map(|c| c + open) else { return vec![word.to_string()] };
    let (head, tail) = (&word[..open], &word[close + 1..]);
    let mut out = Vec::new();
    for alt in word[open + 1..close].split(',') {
        for rest in expand_alternatives(tail) {
            out.push(format!("{head}{alt}{rest}"));
        }
    }
    out
}

/// `*`-only glob matching, iterative with one backtrack point.
fn glob(p: &[u8], s: &[u8]) -> bool {
    let (mut pi, mut si) = (0, 0);
    let mut star: Option<(usize, usize)> = None;
    while si < s.len() {
        if pi < p.len() && p[pi] == b'*' {
            star = Some((pi, si));
            pi += 1;
        } else if pi < p.len() && p[pi] == s[si] {
            pi += 1;
            si += 1;
        } else if let Some((sp, ss)) = star {
            pi = sp + 1;
            si = ss + 1;
            star = Some((sp, ss + 1));
        } else {
            return false;
        }
    }
    while pi < p.len() && p[pi] == b'*' {
        pi += 1;
    }
    pi == p.len()
}

#[cfg(test)]
mod tests {
    use super::*;
    use readi_grammar::diag::Span;

    fn pat(text: &str) -> Pattern {
        let segments = text
            .split('.')
            .map(|s| if s == "**" { PatternSeg::AnyDepth } else { PatternSeg::Word(s.to_string()) })
            .collect();
        Pattern { segments, text: text.to_string(), span: Span::default() }
    }

    #[test]
    fn globs_within_a_segment() {
        assert!(word_matches("bn*", "bn2"));
        assert!(word_matches("*", "0"));
        assert!(word_matches("l*r*1", "layer1"));
        assert!(!word_matches("bn*", "conv1"));
        assert!(word_matches("{q,k,v}", "k"));
        assert!(!word_matches("{q,k,v}", "proj"));
        assert!(word_matches("bn{1,2}", "bn2"));
        assert!(!word_matches("bn{1,2}", "bn3"));
    }

    #[test]
    fn prefixes_select_everything_below() {
        assert!(selects(&pat("head"), "head.cls.0"));
        assert!(selects(&pat("head.*"), "head.cls.0"));
        assert!(!selects(&pat("head"), "heads.cls"));
        assert!(selects(&pat("blocks.*.attn.{q,k,v}"), "blocks.3.attn.v"));
        assert!(!selects(&pat("blocks.*.attn.{q,k,v}"), "blocks.3.attn.proj"));
    }

    #[test]
    fn double_star_spans_any_depth() {
        assert!(selects(&pat("**.bn2"), "layer1.0.bn2"));
        assert!(selects(&pat("**.bn2"), "bn2"));
        assert!(selects(&pat("layer1.**.bn2"), "layer1.0.bn2"));
        assert!(!matches_exactly(&pat("layer1.**"), "layer2.0"));
        assert!(matches_exactly(&pat("fc.bias"), "fc.bias"));
    }
}
