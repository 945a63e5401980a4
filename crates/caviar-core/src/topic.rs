//! Topics in NATS subject syntax.
//!
//! A topic is a dot-separated list of non-empty tokens (`3D.mobility.positions`).
//! A subscription pattern may also use the NATS wildcards: `*` matches exactly one
//! token and `>` (only as the last token) matches one or more remaining tokens.
//! Keeping NATS's exact rules means a topic that works in-process works unchanged
//! on a NATS server.

use std::fmt;

/// Why a topic or pattern was rejected.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("invalid {what} '{text}': {reason}")]
pub struct TopicError {
    pub what: &'static str,
    pub text: String,
    pub reason: &'static str,
}

fn check_tokens(text: &str, what: &'static str, wildcards: bool) -> Result<(), TopicError> {
    let err = |reason| TopicError {
        what,
        text: text.to_string(),
        reason,
    };
    if text.is_empty() {
        return Err(err("it is empty"));
    }
    let tokens: Vec<&str> = text.split('.').collect();
    for (i, token) in tokens.iter().enumerate() {
        if token.is_empty() {
            return Err(err(
                "it has an empty token (leading, trailing or double '.')",
            ));
        }
        if token.chars().any(|c| c.is_whitespace()) {
            return Err(err("tokens may not contain whitespace"));
        }
        let is_wild = *token == "*" || *token == ">";
        if !wildcards && (token.contains('*') || token.contains('>')) {
            return Err(err(
                "a published topic may not contain the wildcards '*' or '>'",
            ));
        }
        if wildcards && !is_wild && (token.contains('*') || token.contains('>')) {
            return Err(err(
                "a wildcard must be a whole token ('a.*.c', not 'a.b*')",
            ));
        }
        if *token == ">" && i + 1 != tokens.len() {
            return Err(err("'>' may only be the last token"));
        }
    }
    Ok(())
}

/// Checks that `topic` can be published (no wildcards).
pub fn validate_topic(topic: &str) -> Result<(), TopicError> {
    check_tokens(topic, "topic", false)
}

#[derive(Debug, Clone, PartialEq, Eq)]
enum Token {
    Literal(String),
    One,
    Rest,
}

/// A compiled subscription pattern.
#[derive(Clone, PartialEq, Eq)]
pub struct Pattern {
    text: String,
    tokens: Vec<Token>,
}

impl Pattern {
    pub fn new(text: &str) -> Result<Self, TopicError> {
        check_tokens(text, "subscription pattern", true)?;
        let tokens = text
            .split('.')
            .map(|t| match t {
                "*" => Token::One,
                ">" => Token::Rest,
                lit => Token::Literal(lit.to_string()),
            })
            .collect();
        Ok(Pattern {
            text: text.to_string(),
            tokens,
        })
    }

    pub fn as_str(&self) -> &str {
        &self.text
    }

    /// True if the (wildcard-free) `topic` matches this pattern.
    pub fn matches(&self, topic: &str) -> bool {
        let mut parts = topic.split('.');
        for token in &self.tokens {
            match token {
                Token::Rest => return parts.next().is_some(),
                Token::One => {
                    if parts.next().is_none() {
                        return false;
                    }
                }
                Token::Literal(lit) => match parts.next() {
                    Some(p) if p == lit => {}
                    _ => return false,
                },
            }
        }
        parts.next().is_none()
    }

    /// True if some topic matches both patterns (e.g. `a.*` and `*.b` share `a.b`).
    pub fn overlaps(&self, other: &Pattern) -> bool {
        fn tokens_overlap(a: &[Token], b: &[Token]) -> bool {
            match (a.first(), b.first()) {
                (None, None) => true,
                // `>` takes one or more tokens: whatever is left on the other side.
                (Some(Token::Rest), Some(_)) | (Some(_), Some(Token::Rest)) => true,
                (None, Some(_)) | (Some(_), None) => false,
                (Some(x), Some(y)) => {
                    let same = match (x, y) {
                        (Token::Literal(p), Token::Literal(q)) => p == q,
                        _ => true,
                    };
                    same && tokens_overlap(&a[1..], &b[1..])
                }
            }
        }
        tokens_overlap(&self.tokens, &other.tokens)
    }
}

/// True if `topic` matches `pattern`; an error if the pattern is not valid.
pub fn matches(pattern: &str, topic: &str) -> Result<bool, TopicError> {
    Ok(Pattern::new(pattern)?.matches(topic))
}

impl fmt::Debug for Pattern {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Pattern({})", self.text)
    }
}

impl fmt::Display for Pattern {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.text)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn m(p: &str, t: &str) -> bool {
        Pattern::new(p).unwrap().matches(t)
    }

    #[test]
    fn literal_patterns_match_only_themselves() {
        assert!(m("3D.mobility.positions", "3D.mobility.positions"));
        assert!(!m("3D.mobility.positions", "3D.mobility"));
        assert!(!m("3D.mobility", "3D.mobility.positions"));
        assert!(!m("3D.mobility.positions", "3d.mobility.positions"));
    }

    #[test]
    fn star_matches_exactly_one_token() {
        assert!(m("communications.*", "communications.throughput"));
        assert!(m("communications.*", "communications.state"));
        assert!(!m("communications.*", "communications"));
        assert!(!m("communications.*", "communications.beam.gains"));
        assert!(m("*.mobility.*", "3D.mobility.positions"));
        assert!(!m("*.mobility.*", "3D.camera.positions"));
    }

    #[test]
    fn greater_than_matches_one_or_more_tokens() {
        assert!(m("3D.>", "3D.mobility.positions"));
        assert!(m("3D.>", "3D.camera"));
        assert!(!m("3D.>", "3D"));
        assert!(m(">", "anything.at.all"));
        assert!(!m("3D.>", "communications.throughput"));
    }

    #[test]
    fn patterns_overlap_when_some_topic_matches_both() {
        let o = |a: &str, b: &str| {
            let (a, b) = (Pattern::new(a).unwrap(), Pattern::new(b).unwrap());
            assert_eq!(a.overlaps(&b), b.overlaps(&a), "symmetric");
            a.overlaps(&b)
        };
        assert!(o("a.b", "a.b"));
        assert!(!o("a.b", "a.c"));
        assert!(o("a.*", "*.b"));
        assert!(!o("a.*", "a"));
        assert!(o("a.>", "a.b.c"));
        assert!(!o("a.>", "a"));
        assert!(o(">", "x"));
        assert!(!o("a.*.c", "a.b.d"));
        assert!(o("*.*", "a.>"));
    }

    #[test]
    fn invalid_patterns_and_topics_are_rejected_with_a_reason() {
        assert!(Pattern::new("a.>.b").unwrap_err().reason.contains("last"));
        assert!(Pattern::new("a..b").unwrap_err().reason.contains("empty"));
        assert!(Pattern::new("a.b*")
            .unwrap_err()
            .reason
            .contains("whole token"));
        assert!(Pattern::new("").is_err());
        assert!(validate_topic("a.*").is_err());
        assert!(validate_topic("a b").is_err());
        assert!(validate_topic(".a").is_err());
        assert!(validate_topic("3D.mobility.positions").is_ok());
    }
}
