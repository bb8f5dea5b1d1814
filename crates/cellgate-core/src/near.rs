//! The names near one that does not exist, for a refusal that says what does exist ("did you
//! mean", or the names themselves when they are few).

/// The names listed whole when none is near: more are counted instead.
const LIST_AT_MOST: usize = 12;

/// Of `known`, the nearest ones if they are near enough to `name` to be a slip, at most `max`:
/// the same but for case, or for the zeros after a program's letter (FANUC counts `O12` and
/// `O0012` as one program), or within an edit or two (a third of a long name).
pub fn nearest<'k>(name: &str, known: &[&'k str], max: usize) -> Vec<&'k str> {
    let wanted = name.to_ascii_lowercase();
    let mut near: Vec<(usize, &'k str)> = known
        .iter()
        // The name itself is no slip: it appeared after the lookup that missed it.
        .filter(|&&k| k != name)
        .filter_map(|&k| {
            let lower = k.to_ascii_lowercase();
            let d = if lower == wanted || unpadded(&lower) == unpadded(&wanted) {
                0
            } else {
                edit_distance(&wanted, &lower)
            };
            // A name of one or two letters is within an edit of too many others.
            (d <= 2.max(k.len() / 3) && d < wanted.len()).then_some((d, k))
        })
        .collect();
    near.sort();
    // The nearest only: `O0012` for `O12`, not also `O1234`.
    let best = near.first().map(|(d, _)| *d);
    near.into_iter()
        .take_while(|(d, _)| Some(*d) == best)
        .take(max)
        .map(|(_, k)| k)
        .collect()
}

/// A letter followed by digits, without the zeros that lead them (`o0012` → `o12`).
fn unpadded(name: &str) -> String {
    let mut chars = name.chars();
    match chars.next() {
        Some(first) if first.is_ascii_alphabetic() => {
            let rest = chars.as_str();
            if !rest.is_empty() && rest.bytes().all(|b| b.is_ascii_digit()) {
                let digits = rest.trim_start_matches('0');
                format!("{first}{}", if digits.is_empty() { "0" } else { digits })
            } else {
                name.to_string()
            }
        }
        _ => name.to_string(),
    }
}

/// What follows "… has no `name`": `; did you mean A or B?`, else the names when there are
/// few (`; its programs are: A, B`), else how many there are and `listed_by` (a command that
/// lists them), or that there are none. `what` names them in the plural (`programs`).
pub fn hint(name: &str, known: &[&str], what: &str, listed_by: &str) -> String {
    let near = nearest(name, known, 3);
    if let Some((last, first)) = near.split_last() {
        let first = if first.is_empty() {
            String::new()
        } else {
            format!("{} or ", first.join(", "))
        };
        return format!("; did you mean {first}{last}?");
    }
    match known.len() {
        0 => format!("; there are no {what}"),
        n if n <= LIST_AT_MOST => format!("; its {what} are: {}", known.join(", ")),
        n => format!("; none of its {n} {what} is near that name ({listed_by} lists them)"),
    }
}

/// Levenshtein distance, by characters.
pub(crate) fn edit_distance(a: &str, b: &str) -> usize {
    let b: Vec<char> = b.chars().collect();
    let mut row: Vec<usize> = (0..=b.len()).collect();
    for (i, ca) in a.chars().enumerate() {
        let mut prev = row[0];
        row[0] = i + 1;
        for (j, cb) in b.iter().enumerate() {
            let cost = usize::from(ca != *cb);
            let next = (row[j + 1] + 1).min(row[j] + 1).min(prev + cost);
            prev = row[j + 1];
            row[j + 1] = next;
        }
    }
    row[b.len()]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_slip_is_near_and_a_stranger_is_not() {
        let known = [
            "O1234",
            "O1235",
            "O0012",
            "lathe-1-O1234-20261201T061500Z",
            "X9",
        ];
        assert_eq!(nearest("O1243", &known, 3), ["O1234", "O1235"]);
        assert_eq!(nearest("o1234", &known, 3)[0], "O1234");
        assert_eq!(nearest("O12", &known, 3), ["O0012"]);
        assert!(nearest("P777777", &known, 3).is_empty());
        // One letter is near every other letter: not a slip.
        assert!(nearest("Q", &["D", "M"], 3).is_empty());
        // Not itself: a name that appeared after the lookup is no "did you mean".
        assert!(nearest("O1234", &["O1234"], 3).is_empty());
    }

    #[test]
    fn the_hint_names_the_near_ones_else_the_few_else_how_many() {
        assert_eq!(
            hint("O1243", &["O1234", "O9"], "programs", "`ls`"),
            "; did you mean O1234?"
        );
        assert_eq!(
            hint("O1244", &["O1234", "O1254", "O9"], "programs", "`ls`"),
            "; did you mean O1234 or O1254?"
        );
        assert_eq!(
            hint("Z", &["A", "B"], "programs", "`ls`"),
            "; its programs are: A, B"
        );
        assert_eq!(
            hint("Z", &[], "programs", "`ls`"),
            "; there are no programs"
        );
        let many: Vec<String> = (0..20).map(|i| format!("P{i}00000")).collect();
        let many: Vec<&str> = many.iter().map(String::as_str).collect();
        assert_eq!(
            hint("Z", &many, "programs", "`ls`"),
            "; none of its 20 programs is near that name (`ls` lists them)"
        );
    }
}
