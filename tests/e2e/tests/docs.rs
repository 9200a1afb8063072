//! The documentation points at what exists: every relative link of `README.md` and
//! `docs/*.md` names a file of the repository and, into a Markdown file, one of its
//! headings; every config a command line runs (`--cfg_file_path=…config/…`) and every
//! `config/…` file named in the text is there; every path in backticks that starts with a
//! folder of the repository (`plugins/zenoh/tests/aimrt_wire.rs`) is there. A renamed
//! section, example, config or file that leaves a page pointing at nothing fails here.
//! Every example config is named by a page, every whole config a page shows passes the
//! config check, and `.ci/run` runs exactly the README's test command.

use std::collections::{HashMap, HashSet};
use std::path::{Path, PathBuf};

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// The pages: `README.md` and every `docs/*.md`, as (path from the root, text).
fn pages() -> Vec<(String, String)> {
    let mut names = vec!["README.md".to_owned()];
    let mut docs: Vec<String> = std::fs::read_dir(root().join("docs"))
        .expect("docs/")
        .filter_map(|e| {
            let name = e.ok()?.file_name().into_string().ok()?;
            name.ends_with(".md").then(|| format!("docs/{name}"))
        })
        .collect();
    docs.sort();
    names.extend(docs);
    names
        .into_iter()
        .map(|n| {
            let text = std::fs::read_to_string(root().join(&n)).expect("a page");
            (n, text)
        })
        .collect()
}

/// Each line of `text` with whether it lies in a fenced code block.
fn lines_with_fences(text: &str) -> Vec<(&str, bool)> {
    let mut fenced = false;
    text.lines()
        .map(|l| {
            if l.trim_start().starts_with("```") {
                fenced = !fenced;
                return (l, true);
            }
            (l, fenced)
        })
        .collect()
}

/// GitHub's anchor of a heading: lower case, letters, digits, `-`, `_` and spaces kept,
/// spaces made `-`.
fn slug(heading: &str) -> String {
    heading
        .trim()
        .to_lowercase()
        .chars()
        .filter(|c| c.is_alphanumeric() || matches!(c, '-' | '_' | ' '))
        .map(|c| if c == ' ' { '-' } else { c })
        .collect()
}

/// The anchors of a page's headings (a repeated heading's later ones get `-1`, `-2`…).
fn anchors(text: &str) -> HashSet<String> {
    let mut seen: HashMap<String, usize> = HashMap::new();
    let mut out = HashSet::new();
    for (line, fenced) in lines_with_fences(text) {
        if fenced {
            continue;
        }
        let hashes = line.chars().take_while(|c| *c == '#').count();
        if hashes == 0 || hashes > 6 || !line[hashes..].starts_with(' ') {
            continue;
        }
        let base = slug(&line[hashes..]);
        let n = seen.entry(base.clone()).or_insert(0);
        out.insert(if *n == 0 {
            base.clone()
        } else {
            format!("{base}-{n}")
        });
        *n += 1;
    }
    out
}

/// The targets of the inline links `](target)` in `line`.
fn links(line: &str) -> Vec<&str> {
    let mut out = Vec::new();
    let mut rest = line;
    while let Some(at) = rest.find("](") {
        rest = &rest[at + 2..];
        let end = rest.find(')').unwrap_or(rest.len());
        out.push(rest[..end].split_whitespace().next().unwrap_or(""));
        rest = &rest[end..];
    }
    out
}

/// The spans in backticks of `line` that are paths into the repository: no spaces or
/// placeholders, a `/`, and a first part that is a folder at the root.
fn repo_paths(line: &str) -> Vec<&str> {
    line.split('`')
        .skip(1)
        .step_by(2)
        .filter(|span| {
            !span.is_empty()
                && span.contains('/')
                && !span.contains(|c: char| c.is_whitespace() || "*<>{}$…|:".contains(c))
        })
        .filter(|span| {
            let first = span.split('/').next().unwrap_or("");
            !matches!(first, "" | "." | "..") && root().join(first).is_dir()
        })
        .collect()
}

/// The files `config/<name>` names in `text` (`.yaml` or `.json5`, not in another folder
/// such as `tests/e2e/corpus/config/`), with `<a|b>` written out:
/// `config/pb_chn_<udp|tcp>_pub.yaml` names `pb_chn_udp_pub.yaml` and `pb_chn_tcp_pub.yaml`.
/// A placeholder without `|` (`config/<name>.yaml`) names nothing.
fn config_names(text: &str) -> Vec<String> {
    let mut out = Vec::new();
    for (at, _) in text.match_indices("config/") {
        let before = &text[..at];
        let own = before.is_empty() || before.ends_with(['/', ' ', '`', '(', '=']);
        if !own || before.ends_with("corpus/") {
            continue;
        }
        let rest = &text[at + "config/".len()..];
        let len = rest
            .find(|c: char| !(c.is_alphanumeric() || "_-.<>|".contains(c)))
            .unwrap_or(rest.len());
        let mut token = rest[..len].trim_end_matches('.');
        if !(token.ends_with(".yaml") || token.ends_with(".json5")) {
            continue;
        }
        let mut names = vec![String::new()];
        while let Some(open) = token.find('<') {
            let Some(close) = token[open..].find('>').map(|c| open + c) else {
                break;
            };
            let alternatives = &token[open + 1..close];
            if !alternatives.contains('|') {
                names.clear();
                break;
            }
            let head = &token[..open];
            names = names
                .iter()
                .flat_map(|n| {
                    alternatives
                        .split('|')
                        .map(move |alt| format!("{n}{head}{alt}"))
                })
                .collect();
            token = &token[close + 1..];
        }
        out.extend(names.into_iter().map(|n| format!("{n}{token}")));
    }
    out
}

#[test]
fn every_link_and_config_the_docs_name_exists() {
    let pages = pages();
    let anchors_of: HashMap<&str, HashSet<String>> = pages
        .iter()
        .map(|(name, text)| (name.as_str(), anchors(text)))
        .collect();
    let mut broken = Vec::new();
    let mut checked = 0;
    for (page, text) in &pages {
        let dir = Path::new(page).parent().unwrap_or(Path::new(""));
        for (n, (line, fenced)) in lines_with_fences(text).into_iter().enumerate() {
            let at = format!("{page}:{}", n + 1);
            if !fenced {
                for target in links(line) {
                    if target.contains("://") || target.starts_with("mailto:") {
                        continue;
                    }
                    checked += 1;
                    let (path, anchor) = target.split_once('#').unwrap_or((target, ""));
                    let file = if path.is_empty() {
                        PathBuf::from(page)
                    } else {
                        dir.join(path)
                    };
                    if !root().join(&file).exists() {
                        broken.push(format!("{at}: {target}: no file {}", file.display()));
                        continue;
                    }
                    if anchor.is_empty() || !path.ends_with(".md") && !path.is_empty() {
                        continue;
                    }
                    let key = normalize(&file);
                    match anchors_of.get(key.as_str()) {
                        Some(known) if known.contains(anchor) => {}
                        Some(_) => broken.push(format!("{at}: {target}: no heading '#{anchor}'")),
                        None => {}
                    }
                }
            }
            if !fenced {
                for path in repo_paths(line) {
                    checked += 1;
                    if !root().join(path.trim_end_matches('/')).exists() {
                        broken.push(format!("{at}: `{path}` does not exist"));
                    }
                }
            }
            // Configs: the ones a command runs (also in code blocks), and the ones the
            // text names.
            let runs = line.contains("--cfg_file_path=");
            if fenced && !runs {
                continue;
            }
            for name in config_names(line) {
                checked += 1;
                if !root().join("config").join(&name).exists() {
                    broken.push(format!("{at}: config/{name} does not exist"));
                }
            }
        }
    }
    assert!(checked > 350, "only {checked} references checked");
    assert!(broken.is_empty(), "{}", broken.join("\n"));
}

/// Every example config under `config/` is named by a page (a command that runs it, or
/// the table of its feature): an example no page names is one no user finds.
#[test]
fn every_example_config_is_named_by_a_page() {
    // `config/<name>`, or the name alone in backticks (`zenoh_pb_chn_sub_with_shm` in a
    // table of pairs, `zenoh_native_c.json5`).
    let named: HashSet<String> = pages()
        .iter()
        .flat_map(|(_, text)| {
            let spans = text.split('`').skip(1).step_by(2);
            let alone = spans
                .filter(|s| !s.contains('/'))
                .flat_map(|s| [s.to_owned(), format!("{s}.yaml")]);
            config_names(text).into_iter().chain(alone)
        })
        .collect();
    let mut unnamed: Vec<String> = std::fs::read_dir(root().join("config"))
        .expect("config/")
        .filter_map(|e| e.ok()?.file_name().into_string().ok())
        .filter(|n| n.ends_with(".yaml") || n.ends_with(".json5"))
        .filter(|n| !named.contains(n))
        .collect();
    unnamed.sort();
    assert!(named.len() > 50, "only {} configs named", named.len());
    assert!(unnamed.is_empty(), "no page names {unnamed:?}");
}

/// `docs/../README.md` → `README.md`, as the pages are keyed.
fn normalize(path: &Path) -> String {
    let mut parts: Vec<&str> = Vec::new();
    for part in path.iter().filter_map(|p| p.to_str()) {
        match part {
            "." => {}
            ".." => {
                parts.pop();
            }
            p => parts.push(p),
        }
    }
    parts.join("/")
}

#[test]
fn the_checks_find_what_they_look_for() {
    assert_eq!(
        slug("Status against issue 21's targets"),
        "status-against-issue-21s-targets"
    );
    assert_eq!(slug("`debug_log` and filters"), "debug_log-and-filters");
    let a = anchors("# A\n## B\n```\n# not a heading\n```\n## B\n");
    assert_eq!(
        a,
        HashSet::from(["a".to_owned(), "b".to_owned(), "b-1".to_owned()])
    );
    assert_eq!(
        links("see [x](a.md#b) and [y](https://e.org) and [z](#c \"t\")"),
        ["a.md#b", "https://e.org", "#c"]
    );
    assert_eq!(
        config_names("run --cfg_file_path=./config/pb_chn.yaml; `config/zenoh_native_a.json5`, tests/e2e/corpus/config/bad.yaml, `config/<name>.yaml`"),
        ["pb_chn.yaml", "zenoh_native_a.json5"]
    );
    assert_eq!(normalize(Path::new("docs/../README.md")), "README.md");
    assert_eq!(
        config_names("`config/pb_chn_<udp|tcp>_benchmark_<sub|pub>.yaml`, ./config/a.json5.")
            .into_iter()
            .collect::<HashSet<_>>(),
        HashSet::from(
            [
                "pb_chn_udp_benchmark_sub.yaml",
                "pb_chn_udp_benchmark_pub.yaml",
                "pb_chn_tcp_benchmark_sub.yaml",
                "pb_chn_tcp_benchmark_pub.yaml",
                "a.json5"
            ]
            .map(String::from)
        )
    );
    assert_eq!(
        repo_paths("`plugins/zenoh/src/wire.rs`, `./dump_cfg.yaml`, `zenoh-1.10.2/src/x.rs`, `docs/<page>.md`, `a b/c`"),
        ["plugins/zenoh/src/wire.rs"]
    );
}

/// The README's two set-up commands: the first `sh` block builds and runs the demo, the
/// second is the test command, and `.ci/run` runs exactly that command.
#[test]
fn ci_runs_exactly_the_readmes_test_command() {
    let readme = std::fs::read_to_string(root().join("README.md")).expect("README.md");
    let blocks: Vec<&str> = readme
        .split("```sh\n")
        .skip(1)
        .filter_map(|b| b.split("```").next())
        .map(str::trim)
        .collect();
    let [demo, test, ..] = blocks[..] else {
        panic!("the README has fewer than two sh blocks");
    };
    assert!(
        demo.starts_with(
            "cargo build --workspace && ./target/debug/aimrt_main --cfg_file_path=./config/"
        ),
        "the first command builds and runs the demo: {demo}"
    );
    assert!(!test.contains('\n'), "the test command is one line: {test}");
    let ci = std::fs::read_to_string(root().join(".ci/run")).expect(".ci/run");
    let runs: Vec<&str> = ci
        .lines()
        .filter(|l| !l.trim_start().starts_with('#'))
        .filter(|l| l.contains("cargo test"))
        .collect();
    assert_eq!(
        runs,
        [format!("step \"tests\" bash -c '{test}'").as_str()],
        ".ci/run must run the README's test command, and no other cargo test"
    );
}

/// Every whole config a page shows (a ```yaml block whose first key is `aimrt:`; not an
/// outline with `{...}` for its sections) passes the runtime's config check: its keys, types and log
/// section, as `aimrt_main` reads them before anything loads. A user copies them as they
/// are.
#[test]
fn every_whole_config_a_page_shows_passes_the_config_check() {
    let mut checked = 0;
    for (page, text) in pages() {
        let mut block: Option<(usize, String)> = None;
        for (n, line) in text.lines().enumerate() {
            let fence = line.trim_start().strip_prefix("```");
            match (&mut block, fence) {
                (None, Some("yaml")) => block = Some((n + 2, String::new())),
                (Some((first, yaml)), Some(_)) => {
                    let whole = yaml
                        .lines()
                        .find(|l| !l.trim().is_empty() && !l.trim_start().starts_with('#'))
                        .is_some_and(|l| l.starts_with("aimrt:"))
                        // An outline with `{...}` for the sections is no config.
                        && !yaml.contains("{...}");
                    if whole {
                        let at = format!("{page}:{first}");
                        if let Err(e) = aimrt_runtime::check_config(&at, yaml) {
                            panic!("the config {at} shows does not pass the check: {e}\n{yaml}");
                        }
                        checked += 1;
                    }
                    block = None;
                }
                (Some((_, yaml)), None) => {
                    yaml.push_str(line);
                    yaml.push('\n');
                }
                _ => {}
            }
        }
    }
    assert!(checked >= 10, "only {checked} configs found in the pages");
}
