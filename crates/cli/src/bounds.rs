//! Bounds of the size flags, checked when the command line is parsed: an absurd size is an
//! error naming the flag (clap prints "invalid value '100000' for '--resolution …'") before
//! anything is allocated, instead of an allocation failure that aborts the process.

fn in_range(text: &str, min: usize, max: usize) -> Result<usize, String> {
    let v: usize = text
        .trim()
        .parse()
        .map_err(|_| format!("`{text}` is not a whole number"))?;
    if !(min..=max).contains(&v) {
        return Err(format!("{v} is not in {min}..={max}"));
    }
    Ok(v)
}

/// A whole number in `MIN..=MAX`.
pub fn size<const MIN: usize, const MAX: usize>(text: &str) -> Result<usize, String> {
    in_range(text, MIN, MAX)
}

/// An image side in pixels in `MIN..=MAX` (the cameras' `u32`).
pub fn side<const MIN: u32, const MAX: u32>(text: &str) -> Result<u32, String> {
    in_range(text, MIN as usize, MAX as usize).map(|v| v as u32)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_outside_the_range_are_errors_that_say_the_range() {
        assert_eq!(size::<16, 8192>("512"), Ok(512));
        assert_eq!(
            size::<16, 8192>("100000").unwrap_err(),
            "100000 is not in 16..=8192"
        );
        assert!(size::<16, 8192>("-1").unwrap_err().contains("whole number"));
        assert_eq!(side::<16, 8192>("8192"), Ok(8192));
        assert!(side::<16, 8192>("8193").is_err());
    }
}
