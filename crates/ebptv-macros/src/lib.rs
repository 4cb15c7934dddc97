//! `#[testkit]`: an internal item that the tests and benches reach.
//!
//! The library crates of ebptv keep their internals crate-private
//! (`pub(crate)`), so that what a user sees is the front door: the stage
//! entry points and their types. The integration tests (tests/) and the
//! benchmarks (benches/) are other crates, yet they measure and check
//! internals (a fit backend against the plain one, a labeller, a kernel).
//! They build the library with its `testkit` feature, and an item marked
//!
//! ```ignore
//! #[ebptv_macros::testkit]
//! pub(crate) fn kernel(..) { .. }
//! ```
//!
//! is `pub` in that build and unchanged (and allowed to be unused) in the
//! default one. The attribute expands to the item twice, once under
//! `#[cfg(feature = "testkit")]` with `pub` visibility and once under
//! `#[cfg(not(feature = "testkit"))]` as written; the `cfg` is read in the
//! crate that uses the attribute, so each crate needs a `testkit` feature.
//! Works on any item with a visibility, methods of inherent impls
//! included. Plain token handling: no parser crate to build.
//!
//! `#[unit_test]`: a white-box test that lives next to the code it tests.
//!
//! A crate's unit tests would need a test harness of their own, which
//! compiles the whole crate a second time (for the root crate, as long as
//! the crate itself). Instead they are compiled into the crate's
//! `testkit` build, which the integration tests link anyway:
//!
//! ```ignore
//! #[cfg(feature = "testkit")]
//! pub(crate) mod tests {
//!     use super::*;
//!     #[ebptv_macros::unit_test]
//!     fn sums() { assert_eq!(add(1, 2), 3) }
//! }
//! ```
//!
//! makes `sums` a `pub(crate)` function (an `#[ignore]` after the attribute
//! is removed here, it only means something to the runner). The crate's
//! build script (crate `ebptv-testgen`) finds every `#[unit_test]`, indexes the
//! functions in the crate (`unit_tests`, testkit only) and writes one
//! `#[test]` per function for the integration-test binary, under the same
//! module path and with the same `#[ignore]`.

use proc_macro::{Delimiter, Group, Ident, Punct, Spacing, Span, TokenStream, TokenTree};

/// Makes the item `pub` when the calling crate's `testkit` feature is on;
/// see the crate documentation.
#[proc_macro_attribute]
pub fn testkit(args: TokenStream, item: TokenStream) -> TokenStream {
    if !args.is_empty() {
        return compile_error("`#[testkit]` takes no arguments");
    }
    let tokens: Vec<TokenTree> = item.into_iter().collect();
    // Outer attributes (doc comments included) come first: `#` `[..]`.
    let mut i = 0;
    while i + 1 < tokens.len()
        && is_punct(&tokens[i], '#')
        && is_group(&tokens[i + 1], Delimiter::Bracket)
    {
        i += 2;
    }
    let (attrs, rest) = tokens.split_at(i);
    // The visibility, if any: `pub` or `pub(..)`.
    let body_start = match rest.first() {
        Some(TokenTree::Ident(id)) if id.to_string() == "pub" => {
            if rest
                .get(1)
                .is_some_and(|t| is_group(t, Delimiter::Parenthesis))
            {
                2
            } else {
                1
            }
        }
        Some(_) => 0,
        None => return compile_error("`#[testkit]` needs an item"),
    };
    let mut out = TokenStream::new();
    // The test kit's build: `pub`.
    out.extend(cfg_attr(false));
    out.extend(attrs.iter().cloned());
    out.extend([TokenTree::Ident(Ident::new("pub", Span::call_site()))]);
    out.extend(rest[body_start..].iter().cloned());
    // The default build: as written, allowed to be unused.
    out.extend(cfg_attr(true));
    out.extend(attribute("allow(dead_code, unused_imports)"));
    out.extend(tokens.iter().cloned());
    out
}

/// A unit test compiled into the `testkit` build; see the crate
/// documentation.
#[proc_macro_attribute]
pub fn unit_test(args: TokenStream, item: TokenStream) -> TokenStream {
    if !args.is_empty() {
        return compile_error("`#[unit_test]` takes no arguments");
    }
    let tokens: Vec<TokenTree> = item.into_iter().collect();
    let mut out = TokenStream::new();
    let mut i = 0;
    while i + 1 < tokens.len()
        && is_punct(&tokens[i], '#')
        && is_group(&tokens[i + 1], Delimiter::Bracket)
    {
        let ignore = matches!(&tokens[i + 1], TokenTree::Group(g)
            if g.stream().into_iter().next().is_some_and(|t| t.to_string() == "ignore"));
        if !ignore {
            out.extend(tokens[i..i + 2].iter().cloned());
        }
        i += 2;
    }
    match tokens.get(i) {
        Some(TokenTree::Ident(id)) if id.to_string() == "fn" => {}
        _ => return compile_error("`#[unit_test]` goes on a private `fn`"),
    }
    out.extend("pub(crate)".parse::<TokenStream>().expect("a visibility"));
    out.extend(tokens[i..].iter().cloned());
    out
}

fn is_punct(t: &TokenTree, c: char) -> bool {
    matches!(t, TokenTree::Punct(p) if p.as_char() == c)
}

fn is_group(t: &TokenTree, d: Delimiter) -> bool {
    matches!(t, TokenTree::Group(g) if g.delimiter() == d)
}

/// `#[cfg(feature = "testkit")]` or, `negated`, `#[cfg(not(feature = "testkit"))]`.
fn cfg_attr(negated: bool) -> TokenStream {
    attribute(if negated {
        r#"cfg(not(feature = "testkit"))"#
    } else {
        r#"cfg(feature = "testkit")"#
    })
}

fn attribute(inner: &str) -> TokenStream {
    let body: TokenStream = inner.parse().expect("a well-formed attribute");
    TokenStream::from_iter([
        TokenTree::Punct(Punct::new('#', Spacing::Alone)),
        TokenTree::Group(Group::new(Delimiter::Bracket, body)),
    ])
}

fn compile_error(msg: &str) -> TokenStream {
    format!("compile_error!({msg:?});")
        .parse()
        .expect("a well-formed error")
}
