//! Tables of the study reports (`slag-bench`, `slag-edge bench`, the evaluations): rows of cells
//! measured first, written afterwards as a GitHub-flavoured Markdown table or as CSV.
//!
//! Cells are text, formatted by the study (units and precision are its choice); the table only
//! lays them out. The Markdown form is compact (no padding): `| a | b |`, one line per row,
//! under a `|---|---:|` alignment line.

use std::fmt;

/// Horizontal alignment of a Markdown column (its cell in the `|---|` line).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Align {
    /// `---`: no alignment given (renders left-aligned).
    #[default]
    Left,
    /// `---:`: right-aligned, for numbers.
    Right,
}

/// A table: a header of column names, one alignment per column and rows of text cells.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Table {
    header: Vec<String>,
    align: Vec<Align>,
    rows: Vec<Vec<String>>,
}

impl Table {
    /// A table with these column names, every column [`Align::Left`].
    pub fn new<S: Into<String>>(header: impl IntoIterator<Item = S>) -> Self {
        let header: Vec<String> = header.into_iter().map(Into::into).collect();
        let align = vec![Align::Left; header.len()];
        Table {
            header,
            align,
            rows: Vec::new(),
        }
    }

    /// A table whose column names are given as one line, separated by `|` (as the header line
    /// of the Markdown table reads; outer bars optional, names trimmed): `"N | dtype | ms"`.
    /// Every column [`Align::Left`].
    pub fn with_header(header: &str) -> Self {
        let h = header.trim();
        let h = h.strip_prefix('|').unwrap_or(h);
        let h = h.strip_suffix('|').unwrap_or(h);
        Table::new(h.split('|').map(str::trim))
    }

    /// The same table with the columns at these indices (0-based) [`Align::Right`]; indices past
    /// the last column are ignored.
    pub fn right(mut self, columns: impl IntoIterator<Item = usize>) -> Self {
        for c in columns {
            if let Some(a) = self.align.get_mut(c) {
                *a = Align::Right;
            }
        }
        self
    }

    /// The same table with every column from index `first` on [`Align::Right`].
    pub fn right_from(self, first: usize) -> Self {
        let n = self.header.len();
        self.right(first..n)
    }

    /// Appends a row. A row with fewer cells than columns is padded with empty cells; extra cells
    /// are kept (the table then has ragged rows, which Markdown renderers cut).
    pub fn row<S: Into<String>>(&mut self, cells: impl IntoIterator<Item = S>) {
        let mut cells: Vec<String> = cells.into_iter().map(Into::into).collect();
        if cells.len() < self.header.len() {
            cells.resize(self.header.len(), String::new());
        }
        self.rows.push(cells);
    }

    /// The table with `rows` appended ([`Table::row`] for each).
    pub fn with_rows<R, S>(mut self, rows: impl IntoIterator<Item = R>) -> Self
    where
        R: IntoIterator<Item = S>,
        S: Into<String>,
    {
        for r in rows {
            self.row(r);
        }
        self
    }

    /// Number of rows (the header not counted).
    pub fn len(&self) -> usize {
        self.rows.len()
    }

    /// Whether the table has no rows.
    pub fn is_empty(&self) -> bool {
        self.rows.is_empty()
    }

    /// The Markdown table: header line, alignment line, one line per row, each ending in `\n`.
    pub fn markdown(&self) -> String {
        self.to_string()
    }

    /// The CSV text (RFC 4180): the header line, then one line per row, each ending in `\n`;
    /// a field holding a comma, a double quote or a line break is quoted (quotes doubled).
    pub fn csv(&self) -> String {
        let mut s = String::new();
        for line in std::iter::once(&self.header).chain(&self.rows) {
            let fields: Vec<String> = line.iter().map(|f| csv_field(f)).collect();
            s.push_str(&fields.join(","));
            s.push('\n');
        }
        s
    }
}

/// One CSV field, quoted when it must be.
pub fn csv_field(s: &str) -> String {
    if s.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

impl fmt::Display for Table {
    /// Writes [`Table::markdown`].
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(f, "| {} |", self.header.join(" | "))?;
        f.write_str("|")?;
        for a in &self.align {
            f.write_str(match a {
                Align::Left => "---|",
                Align::Right => "---:|",
            })?;
        }
        f.write_str("\n")?;
        for r in &self.rows {
            writeln!(f, "| {} |", r.join(" | "))?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn markdown_has_header_alignment_and_one_line_per_row() {
        let mut t = Table::new(["N", "dtype", "ms"]).right([2]);
        t.row(["1M", "f32", "3.5"]);
        t.row(vec!["2M".to_string(), "int8".into()]);
        assert_eq!(
            t.markdown(),
            "| N | dtype | ms |\n|---|---|---:|\n| 1M | f32 | 3.5 |\n| 2M | int8 |  |\n"
        );
        assert_eq!(t.len(), 2);
        let r = Table::with_header("| a | b | c |").right_from(1);
        assert_eq!(r.markdown(), "| a | b | c |\n|---|---:|---:|\n");
        assert!(r.is_empty());
    }

    #[test]
    fn csv_quotes_only_fields_that_need_it() {
        let t = Table::new(["name", "note"]).with_rows([["a", "x, y"], ["b\"c", "plain"]]);
        assert_eq!(t.csv(), "name,note\na,\"x, y\"\n\"b\"\"c\",plain\n");
    }
}
