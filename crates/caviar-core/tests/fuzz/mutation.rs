//! Byte-level mutations of seed inputs, shared by the targets that read bytes.

use proptest::prelude::*;
use proptest::sample::{select, Index};

/// Byte-level mutations of a seed: what a corrupt file, a truncated frame or a typo does.
#[derive(Debug, Clone)]
pub(crate) enum Edit {
    Flip(Index, u8),
    Insert(Index, u8),
    Delete(Index, usize),
    Duplicate(Index, usize),
    Interesting(Index, u8),
    Truncate(Index),
}

pub(crate) fn edit() -> impl Strategy<Value = Edit> {
    prop_oneof![
        (any::<Index>(), 1u8..=255).prop_map(|(i, b)| Edit::Flip(i, b)),
        (any::<Index>(), any::<u8>()).prop_map(|(i, b)| Edit::Insert(i, b)),
        (any::<Index>(), 1usize..64).prop_map(|(i, n)| Edit::Delete(i, n)),
        (any::<Index>(), 1usize..64).prop_map(|(i, n)| Edit::Duplicate(i, n)),
        (any::<Index>(), any::<u8>()).prop_map(|(i, b)| Edit::Interesting(i, b)),
        any::<Index>().prop_map(Edit::Truncate),
    ]
}

/// Bytes that parsers treat specially (quotes, brackets, separators, digits, UTF-8 lead bytes).
const INTERESTING: &[u8] = b"\"'[]{}=.,:#\n\\0-9 \x00\xff\xc3\xe2*>eE+";

pub(crate) fn apply(mut data: Vec<u8>, edits: &[Edit]) -> Vec<u8> {
    for e in edits {
        let n = data.len();
        match *e {
            Edit::Flip(ref i, b) if n > 0 => data[i.index(n)] ^= b,
            Edit::Insert(ref i, b) => data.insert(i.index(n + 1), b),
            Edit::Delete(ref i, len) if n > 0 => {
                let at = i.index(n);
                data.drain(at..(at + len).min(n));
            }
            Edit::Duplicate(ref i, len) if n > 0 => {
                let at = i.index(n);
                let chunk = data[at..(at + len).min(n)].to_vec();
                data.splice(at..at, chunk);
            }
            Edit::Interesting(ref i, b) if n > 0 => {
                data[i.index(n)] = INTERESTING[b as usize % INTERESTING.len()]
            }
            Edit::Truncate(ref i) => data.truncate(i.index(n + 1)),
            _ => {}
        }
    }
    data
}

/// A seed from `seeds`, mutated by up to `max_edits` edits (sometimes none).
pub(crate) fn mutated(seeds: Vec<Vec<u8>>, max_edits: usize) -> impl Strategy<Value = Vec<u8>> {
    (select(seeds), prop::collection::vec(edit(), 0..=max_edits))
        .prop_map(|(seed, edits)| apply(seed, &edits))
}
