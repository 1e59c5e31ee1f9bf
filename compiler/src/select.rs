//! Path patterns of adaptation selectors, matched against dotted node paths.
//!
//! A pattern is a list of segments. A segment matches one path segment: `*` matches any
//! run of characters within it, `{a,b}` either alternative (`bn{1,2}`, `{q,k,v}`). The
//! segment `**` matches any number of path segments, including none. A pattern *selects*
//! a path when it matches the whole path or any prefix of it: selecting a scope selects
//! everything under it (`head` and `head.*` both select `head.cls.0.weight`'s layer).
//!
//! Matching is polynomial, whatever the pattern: a pattern is compiled once
//! ([`Matcher::new`]) and run as a nondeterministic automaton, keeping the set of places
//! it can be in, never by backtracking or by expanding alternatives. A segment glob runs
//! over the characters of one path segment (`O(glob * segment)`), the list of segments
//! over the path's segments (`O(pattern * depth)` segment matches), and which globs
//! match which path segment text is remembered, so a graph whose paths repeat `0`,
//! `conv1`, `bn1` pays for each distinct text once. Ten `**` on a 30-deep path, or 22
//! `{a,b}` groups in one segment, take microseconds. Patterns longer than
//! [`MAX_PATTERN_LEN`] or with more than [`MAX_ALTERNATIVES`] brace alternatives are
//! refused at their span, so that the work is bounded by the graph's size.

use std::cell::RefCell;
use std::collections::HashMap;

use readi_grammar::ast::{Pattern, PatternSeg};
use readi_grammar::diag::{Code, Diagnostic};

/// Longest pattern, in bytes, a selector may have.
pub const MAX_PATTERN_LEN: usize = 256;
/// Most `{a,b}` alternatives, over all its groups, a pattern may have.
pub const MAX_ALTERNATIVES: usize = 64;

/// One piece of a segment glob.
#[derive(Clone, Debug, PartialEq)]
enum Tok {
    Byte(u8),
    /// `*`: any run of characters.
    Star,
    /// `{a,b}`: one of the alternatives, each a glob without braces.
    Alt(Vec<Vec<Tok>>),
}

#[derive(Clone, Debug, PartialEq)]
enum Seg {
    /// `**`.
    AnyDepth,
    Glob(Vec<Tok>),
}

/// A compiled pattern; see the module documentation.
#[derive(Debug)]
pub struct Matcher {
    segs: Vec<Seg>,
    /// Whether glob `i` (an index into `segs`) matches a path segment text.
    memo: RefCell<HashMap<(usize, String), bool>>,
}

impl Matcher {
    /// Compiles `pattern`; an error at its span if it is over the limits.
    pub fn new(pattern: &Pattern) -> Result<Matcher, Diagnostic> {
        let too_complex = |what: String| {
            Diagnostic::error(Code::Limit, format!("this selector is too complex: {what}"))
                .with_primary(pattern.span, "too complex")
                .with_note("use `*` and `**` to select many layers, or split the selector over several rules")
        };
        if pattern.text.len() > MAX_PATTERN_LEN {
            return Err(too_complex(format!(
                "it is {} characters long, over the limit of {MAX_PATTERN_LEN}",
                pattern.text.len()
            )));
        }
        let mut alternatives = 0usize;
        let segs: Vec<Seg> = pattern
            .segments
            .iter()
            .map(|s| match s {
                PatternSeg::AnyDepth => Seg::AnyDepth,
                PatternSeg::Word(w) => Seg::Glob(compile_glob(w, &mut alternatives)),
            })
            .collect();
        if alternatives > MAX_ALTERNATIVES {
            return Err(too_complex(format!(
                "it has {alternatives} `{{a,b}}` alternatives, over the limit of {MAX_ALTERNATIVES}"
            )));
        }
        Ok(Matcher { segs, memo: RefCell::new(HashMap::new()) })
    }

    /// Whether the pattern matches `path` or one of its prefixes (of at least one segment).
    pub fn selects(&self, path: &str) -> bool {
        let segs = split(path);
        let ends = self.run(&segs);
        ends.iter().skip(1).any(|&e| e)
    }

    /// Whether the pattern matches exactly `path`.
    pub fn matches_exactly(&self, path: &str) -> bool {
        let segs = split(path);
        self.run(&segs)[segs.len()]
    }

    /// The set of path positions (`0..=segs.len()`) the pattern can end at, having
    /// consumed `segs[..k]`. Segments only move forward and each looks at one path
    /// segment, so a prefix of the path ends where the whole does, cut at its length.
    fn run(&self, segs: &[&str]) -> Vec<bool> {
        let n = segs.len();
        let mut at = vec![false; n + 1];
        at[0] = true;
        for (i, seg) in self.segs.iter().enumerate() {
            let mut next = vec![false; n + 1];
            match seg {
                Seg::AnyDepth => {
                    let mut reached = false;
                    for k in 0..=n {
                        reached |= at[k];
                        next[k] = reached;
                    }
                }
                Seg::Glob(glob) => {
                    for k in 0..n {
                        if at[k] && self.glob_matches(i, glob, segs[k]) {
                            next[k + 1] = true;
                        }
                    }
                }
            }
            if !next.iter().any(|&b| b) {
                return next;
            }
            at = next;
        }
        at
    }

    fn glob_matches(&self, i: usize, glob: &[Tok], text: &str) -> bool {
        if let Some(&m) = self.memo.borrow().get(&(i, text.to_string())) {
            return m;
        }
        let m = glob_matches(glob, text.as_bytes());
        self.memo.borrow_mut().insert((i, text.to_string()), m);
        m
    }
}

fn split(path: &str) -> Vec<&str> {
    if path.is_empty() { Vec::new() } else { path.split('.').collect() }
}

/// `bn{1,2}*` to its pieces, counting the alternatives. Nested braces are not part of the
/// syntax; an unclosed `{` is a literal character (the grammar admits neither).
fn compile_glob(word: &str, alternatives: &mut usize) -> Vec<Tok> {
    let plain = |s: &str| s.bytes().map(|b| if b == b'*' { Tok::Star } else { Tok::Byte(b) }).collect::<Vec<_>>();
    let mut out = Vec::new();
    let mut rest = word;
    while let Some(open) = rest.find('{') {
        let Some(close) = rest[open..].find('}').map(|c| c + open) else { break };
        out.extend(plain(&rest[..open]));
        let alts: Vec<Vec<Tok>> = rest[open + 1..close].split(',').map(plain).collect();
        *alternatives = alternatives.saturating_add(alts.len());
        out.push(Tok::Alt(alts));
        rest = &rest[close + 1..];
    }
    out.extend(plain(rest));
    out
}

/// Whether a glob matches all of `s`: the set of positions of `s` the glob can have
/// reached, token by token.
fn glob_matches(glob: &[Tok], s: &[u8]) -> bool {
    let mut at = vec![false; s.len() + 1];
    at[0] = true;
    advance(glob, s, &mut at);
    at[s.len()]
}

/// Moves the position set `at` over `toks`.
fn advance(toks: &[Tok], s: &[u8], at: &mut Vec<bool>) {
    for t in toks {
        let mut next = vec![false; s.len() + 1];
        match t {
            Tok::Byte(b) => {
                for k in 0..s.len() {
                    next[k + 1] = at[k] && s[k] == *b;
                }
            }
            Tok::Star => {
                let mut reached = false;
                for k in 0..=s.len() {
                    reached |= at[k];
                    next[k] = reached;
                }
            }
            Tok::Alt(alts) => {
                for alt in alts {
                    let mut a = at.clone();
                    advance(alt, s, &mut a);
                    for (n, x) in next.iter_mut().zip(a) {
                        *n |= x;
                    }
                }
            }
        }
        *at = next;
        if !at.iter().any(|&b| b) {
            return;
        }
    }
}

/// Whether one segment glob (with `*` and `{a,b}`) matches one path segment.
pub fn word_matches(word: &str, seg: &str) -> bool {
    glob_matches(&compile_glob(word, &mut 0), seg.as_bytes())
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

    fn m(text: &str) -> Matcher {
        Matcher::new(&pat(text)).expect("within the limits")
    }

    fn selects(text: &str, path: &str) -> bool {
        m(text).selects(path)
    }

    fn matches_exactly(text: &str, path: &str) -> bool {
        m(text).matches_exactly(path)
    }

    #[test]
    fn globs_within_a_segment() {
        assert!(word_matches("bn*", "bn2"));
        assert!(word_matches("*", "0"));
        assert!(word_matches("*", ""));
        assert!(word_matches("l*r*1", "layer1"));
        assert!(!word_matches("l*r*1", "layer12"));
        assert!(!word_matches("bn*", "conv1"));
        assert!(word_matches("{q,k,v}", "k"));
        assert!(!word_matches("{q,k,v}", "proj"));
        assert!(word_matches("bn{1,2}", "bn2"));
        assert!(!word_matches("bn{1,2}", "bn3"));
        assert!(word_matches("{conv,bn}{1,2}", "bn1"));
        assert!(!word_matches("{conv,bn}{1,2}", "bn12"));
        // Stars inside alternatives, and an empty alternative.
        assert!(word_matches("a{*x,y}b", "aqqxb"));
        assert!(word_matches("a{,y}b", "ab"));
        assert!(!word_matches("a{*x,y}b", "aqqb"));
    }

    #[test]
    fn prefixes_select_everything_below() {
        assert!(selects("head", "head.cls.0"));
        assert!(selects("head.*", "head.cls.0"));
        assert!(!selects("head", "heads.cls"));
        assert!(selects("blocks.*.attn.{q,k,v}", "blocks.3.attn.v"));
        assert!(!selects("blocks.*.attn.{q,k,v}", "blocks.3.attn.proj"));
        assert!(!selects("head", ""));
        assert!(!selects("**", ""));
    }

    #[test]
    fn double_star_spans_any_depth() {
        assert!(selects("**.bn2", "layer1.0.bn2"));
        assert!(selects("**.bn2", "bn2"));
        assert!(selects("layer1.**.bn2", "layer1.0.bn2"));
        assert!(selects("layer1.**.bn2", "layer1.bn2"));
        assert!(!matches_exactly("layer1.**", "layer2.0"));
        assert!(matches_exactly("layer1.**", "layer1"));
        assert!(matches_exactly("fc.bias", "fc.bias"));
        assert!(!matches_exactly("fc", "fc.bias"));
        assert!(matches_exactly("**.**.b.**", "a.b"));
        assert!(!matches_exactly("**.b.**.b", "a.b"));
    }

    /// What the old backtracking matcher took exponential time on: checked against a
    /// direct reading of the definition on small cases, and fast on large ones.
    #[test]
    fn hostile_patterns_are_fast() {
        let deep: Vec<String> = (0..30).map(|i| format!("s{i}")).collect();
        let path = deep.join(".");
        let ten = ["**"; 10].join(".");
        let mut p = format!("{ten}.x");
        assert!(!m(&p).selects(&path));
        p = format!("{ten}.s29");
        assert!(m(&p).matches_exactly(&path));
        let groups = "{a,b}".repeat(22);
        let word = "ab".repeat(11);
        assert!(word_matches(&groups, &word));
        assert!(!word_matches(&groups, &format!("{word}c")));
        // `*` runs: a{*}... with many stars against a long near-miss.
        let stars = "a*".repeat(40) + "b";
        assert!(!word_matches(&stars, &"a".repeat(200)));
    }

    #[test]
    fn limits_are_errors_at_the_pattern() {
        let long = "a".repeat(MAX_PATTERN_LEN + 1);
        let e = Matcher::new(&pat(&long)).expect_err("too long");
        assert!(e.message.contains("characters long"), "{}", e.message);
        let many = "{a,b}".repeat(MAX_ALTERNATIVES / 2 + 1);
        let e = Matcher::new(&pat(&many)).expect_err("too many alternatives");
        assert!(e.message.contains("alternatives"), "{}", e.message);
        assert!(Matcher::new(&pat(&"{a,b}".repeat(MAX_ALTERNATIVES / 2))).is_ok());
    }

    /// The automaton agrees with a backtracking reading of the definition.
    #[test]
    fn agrees_with_the_definition() {
        fn naive_seg(p: &[u8], s: &[u8]) -> bool {
            match p.split_first() {
                None => s.is_empty(),
                Some((b'*', rest)) => (0..=s.len()).any(|k| naive_seg(rest, &s[k..])),
                Some((c, rest)) => s.first() == Some(c) && naive_seg(rest, &s[1..]),
            }
        }
        fn naive(p: &[&str], s: &[&str]) -> bool {
            match p.split_first() {
                None => s.is_empty(),
                Some((&"**", rest)) => (0..=s.len()).any(|k| naive(rest, &s[k..])),
                Some((w, rest)) => !s.is_empty() && naive_seg(w.as_bytes(), s[0].as_bytes()) && naive(rest, &s[1..]),
            }
        }
        let pats = ["a", "*", "**", "a.**", "**.b", "a*.**.*b", "**.**", "a.*.b", "*a*.**"];
        let paths = ["a", "b", "a.b", "ab.b", "a.a.b", "ba.x.ab", "a.x.y.b", "xay"];
        for p in pats {
            let ps: Vec<&str> = p.split('.').collect();
            for path in paths {
                let s: Vec<&str> = path.split('.').collect();
                assert_eq!(matches_exactly(p, path), naive(&ps, &s), "{p} on {path}");
                let any_prefix = (1..=s.len()).any(|k| naive(&ps, &s[..k]));
                assert_eq!(selects(p, path), any_prefix, "{p} selects {path}");
            }
        }
    }
}
