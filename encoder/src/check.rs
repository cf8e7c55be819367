//! Range checks of settings, one line per setting in the `validate` methods.

use slag_common::{Error, Result};

/// `Ok(())` when `ok`; else [`Error::Param`] naming the setting `name`, with the `value` given
/// and what is `expected` instead (the domain, with an example where it helps).
pub(crate) fn require(
    ok: bool,
    name: &'static str,
    value: impl std::fmt::Display,
    expected: impl Into<String>,
) -> Result<()> {
    if ok {
        Ok(())
    } else {
        Err(Error::param(name, value, expected))
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)] // tests fail loudly on purpose
mod tests {
    use super::*;

    #[test]
    fn a_failed_check_names_the_setting_its_value_and_the_domain() {
        assert!(require(true, "k", 1, "k > 0").is_ok());
        let e = require(false, "k", -1, "k > 0").unwrap_err();
        assert!(
            matches!(&e, Error::Param { name: "k", value, expected } if value == "-1" && expected == "k > 0"),
            "{e:?}"
        );
    }
}
