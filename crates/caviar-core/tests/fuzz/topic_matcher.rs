//! The topic matcher, against a reference written from NATS's rules.

use proptest::prelude::*;
use proptest::sample::select;

use caviar_core::topic::{validate_topic, Pattern};

use crate::harness::fuzz;

/// NATS subject rules, independently: non-empty tokens without whitespace; `*` and `>`
/// only as whole tokens of a pattern, `>` only last.
fn reference_valid(text: &str, wildcards: bool) -> bool {
    let tokens: Vec<&str> = text.split('.').collect();
    !text.is_empty()
        && tokens.iter().enumerate().all(|(i, t)| {
            !t.is_empty()
                && !t.chars().any(char::is_whitespace)
                && if wildcards {
                    (*t == "*" || *t == ">" || !(t.contains('*') || t.contains('>')))
                        && (*t != ">" || i + 1 == tokens.len())
                } else {
                    !(t.contains('*') || t.contains('>'))
                }
        })
}

fn reference_matches(pattern: &[&str], topic: &[&str]) -> bool {
    match (pattern.split_first(), topic.split_first()) {
        (None, None) => true,
        (Some((&">", _)), Some(_)) => true,
        (Some((p, prest)), Some((t, trest))) => {
            (*p == "*" || p == t) && reference_matches(prest, trest)
        }
        _ => false,
    }
}

fn token() -> impl Strategy<Value = String> {
    prop_oneof![
        6 => select(vec!["a", "b", "ab", "*", ">"]).prop_map(str::to_string),
        1 => select(vec!["", " ", "a*", ">b", "\t", "é", "*>"]).prop_map(str::to_string),
        1 => "\\PC{0,3}",
    ]
}

fn subject() -> impl Strategy<Value = String> {
    prop::collection::vec(token(), 1..5).prop_map(|t| t.join("."))
}

#[test]
fn the_topic_matcher_agrees_with_nats_rules() {
    fuzz(
        "topic matcher",
        20_000,
        (subject(), subject(), subject()),
        |(p, q, t)| {
            prop_assert_eq!(
                validate_topic(&t).is_ok(),
                reference_valid(&t, false),
                "topic {:?}",
                t
            );
            let pattern = Pattern::new(&p);
            prop_assert_eq!(
                pattern.is_ok(),
                reference_valid(&p, true),
                "pattern {:?}",
                p
            );
            if let Err(e) = &pattern {
                prop_assert!(e.to_string().contains(&p), "{}", e);
            }
            let (Ok(pattern), true) = (pattern, reference_valid(&t, false)) else {
                return Ok(());
            };
            let split = |s: &str| s.split('.').map(str::to_string).collect::<Vec<_>>();
            let (pt, tt) = (split(&p), split(&t));
            let (pt, tt): (Vec<&str>, Vec<&str>) = (
                pt.iter().map(String::as_str).collect(),
                tt.iter().map(String::as_str).collect(),
            );
            prop_assert_eq!(
                pattern.matches(&t),
                reference_matches(&pt, &tt),
                "{:?} ~ {:?}",
                p,
                t
            );
            // Overlap: true exactly when some topic matches both (searched over the
            // patterns' own literals and one fresh token, up to one token longer).
            let Ok(other) = Pattern::new(&q) else {
                return Ok(());
            };
            let mut alphabet: Vec<String> = p
                .split('.')
                .chain(q.split('.'))
                .filter(|t| *t != "*" && *t != ">")
                .map(str::to_string)
                .collect();
            alphabet.push("zz".into());
            alphabet.sort();
            alphabet.dedup();
            let longest = p.split('.').count().max(q.split('.').count()) + 1;
            let mut witness = false;
            let mut topics: Vec<Vec<String>> = vec![vec![]];
            for _ in 0..longest {
                topics = topics
                    .into_iter()
                    .flat_map(|t| {
                        alphabet.iter().map(move |a| {
                            let mut t = t.clone();
                            t.push(a.clone());
                            t
                        })
                    })
                    .collect();
                witness |= topics.iter().any(|t| {
                    let s = t.join(".");
                    pattern.matches(&s) && other.matches(&s)
                });
            }
            prop_assert_eq!(
                pattern.overlaps(&other),
                witness,
                "{:?} overlaps {:?}",
                p,
                q
            );
            Ok(())
        },
    );
}
