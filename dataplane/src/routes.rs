//! One queryable per hosted service, `swarmrec/v1/<swarm>/<kind>/<robot>/**`, and the
//! endpoint a query names found in a map (a caller-bound endpoint's requests name their
//! sender in one more chunk, `<endpoint>/<caller>`: `runtime::CALLER_BOUND`).
//!
//! Why: zenoh's session matches an incoming query against every queryable it declared,
//! one key-expression intersection each. A process hosting 50 robots declared one
//! queryable per endpoint, about 700, and `keyexpr::intersects` was 29 % of its CPU in a
//! 100-robot lock-step run. One per service is 150, and finding the endpoint is a hash
//! lookup.
//!
//! The answers are those of one queryable per endpoint: a query names one endpoint and
//! that endpoint answers; a query with wildcards (`.../index-shard/3/*`, `.../**`) is
//! served by every endpoint whose key it intersects, each replying on its own key; a
//! query naming an endpoint the service does not have gets no reply, as no queryable
//! would have answered it. The router's access control allows exactly this key to the
//! service's identity (`<kind>/<robot>/**`).

use std::collections::HashMap;

use zenoh::key_expr::{keyexpr, OwnedKeyExpr};

use crate::runtime::caller_bound;

/// What a route is given: something with the key expression it was asked on.
pub trait Keyed: Clone {
    fn key(&self) -> &str;
}

impl Keyed for zenoh::query::Query {
    fn key(&self) -> &str {
        self.key_expr().as_str()
    }
}

/// Serves one endpoint's query (on the calling thread, or handed to the endpoint's own).
pub type Route<Q> = Box<dyn Fn(Q) + Send + Sync>;

/// The endpoints of one service behind its one queryable.
pub struct Routes<Q> {
    /// `swarmrec/v1/<swarm>/<kind>/<robot>/`
    prefix: String,
    kind: String,
    by_name: HashMap<String, usize>,
    /// In the order added: (the endpoint's full key, its route).
    routes: Vec<(OwnedKeyExpr, Route<Q>)>,
}

impl<Q: Keyed> Routes<Q> {
    pub fn new(swarm: &str, kind: &str, robot: u32) -> Self {
        Routes {
            prefix: format!("swarmrec/v1/{swarm}/{kind}/{robot}/"),
            kind: kind.to_owned(),
            by_name: HashMap::new(),
            routes: Vec::new(),
        }
    }

    /// The key to declare: every endpoint of the service.
    pub fn key(&self) -> String {
        format!("{}**", self.prefix)
    }

    pub fn add(&mut self, name: &str, route: Route<Q>) -> anyhow::Result<()> {
        // A caller-bound endpoint answers at `<name>/<caller>` (and refuses `<name>` alone).
        let tail = if caller_bound(&self.kind, name) { "/**" } else { "" };
        let key = OwnedKeyExpr::try_from(format!("{}{name}{tail}", self.prefix))
            .map_err(|e| anyhow::anyhow!("endpoint {name}: {e}"))?;
        if self.by_name.insert(name.to_owned(), self.routes.len()).is_some() {
            anyhow::bail!("endpoint {name} declared twice");
        }
        self.routes.push((key, route));
        Ok(())
    }

    /// The endpoints a query on `key` asks, in the order they were added.
    fn matching(&self, key: &str) -> Vec<usize> {
        // A key without wildcards that zenoh delivered here is `<prefix><endpoint>`, or
        // `<prefix><endpoint>/<caller>` for a caller-bound endpoint.
        if let Some(rest) = key
            .strip_prefix(self.prefix.as_str())
            .filter(|r| !r.contains(['*', '$']))
        {
            let (name, tail) = rest.split_once('/').map_or((rest, None), |(n, t)| (n, Some(t)));
            let bound = caller_bound(&self.kind, name);
            let one_chunk = tail.is_none() || (bound && tail.is_some_and(|t| !t.contains('/')));
            return match self.by_name.get(name) {
                Some(&i) if one_chunk => vec![i],
                _ => Vec::new(),
            };
        }
        match keyexpr::new(key) {
            Ok(asked) => (0..self.routes.len())
                .filter(|&i| asked.intersects(&self.routes[i].0))
                .collect(),
            Err(_) => Vec::new(),
        }
    }

    /// Serves `query` on each endpoint it asks; none: no reply (dropping the query ends it).
    pub fn serve(&self, query: Q) {
        let mut matched = self.matching(query.key()).into_iter();
        let Some(last) = matched.next_back() else {
            return;
        };
        for i in matched {
            (self.routes[i].1)(query.clone());
        }
        (self.routes[last].1)(query);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::{Arc, Mutex};

    #[derive(Clone)]
    struct Asked(String);

    impl Keyed for Asked {
        fn key(&self) -> &str {
            &self.0
        }
    }

    fn routes(served: &Arc<Mutex<Vec<String>>>) -> Routes<Asked> {
        let mut r = Routes::new("s", "index-shard", 3);
        for name in ["query", "store", "info"] {
            let served = served.clone();
            r.add(
                name,
                Box::new(move |q: Asked| served.lock().unwrap().push(format!("{name} <- {}", q.0))),
            )
            .unwrap();
        }
        r
    }

    fn ask(key: &str) -> Vec<String> {
        let served = Arc::new(Mutex::new(Vec::new()));
        routes(&served).serve(Asked(key.to_owned()));
        let got = served.lock().unwrap().clone();
        got
    }

    #[test]
    fn a_query_naming_an_endpoint_is_served_by_that_endpoint_alone() {
        assert_eq!(
            ask("swarmrec/v1/s/index-shard/3/store"),
            ["store <- swarmrec/v1/s/index-shard/3/store"]
        );
        assert_eq!(routes(&Arc::default()).key(), "swarmrec/v1/s/index-shard/3/**");
        // A caller-bound endpoint's request names its sender.
        assert_eq!(
            ask("swarmrec/v1/s/index-shard/3/store/2"),
            ["store <- swarmrec/v1/s/index-shard/3/store/2"]
        );
        // Another endpoint with a chunk too many would have had no queryable.
        assert!(ask("swarmrec/v1/s/index-shard/3/info/2").is_empty());
    }

    #[test]
    fn a_wildcard_query_is_served_by_every_endpoint_it_intersects_in_order() {
        assert_eq!(
            ask("swarmrec/v1/s/index-shard/3/*"),
            [
                "query <- swarmrec/v1/s/index-shard/3/*",
                "store <- swarmrec/v1/s/index-shard/3/*",
                "info <- swarmrec/v1/s/index-shard/3/*"
            ]
        );
        assert_eq!(ask("swarmrec/v1/s/*/3/info"), ["info <- swarmrec/v1/s/*/3/info"]);
        assert_eq!(
            ask("swarmrec/v1/s/**"),
            [
                "query <- swarmrec/v1/s/**",
                "store <- swarmrec/v1/s/**",
                "info <- swarmrec/v1/s/**"
            ]
        );
        assert_eq!(
            ask("swarmrec/v1/s/index-shard/3/st$*"),
            ["store <- swarmrec/v1/s/index-shard/3/st$*"]
        );
    }

    #[test]
    fn a_query_for_an_endpoint_the_service_lacks_gets_no_answer() {
        assert!(ask("swarmrec/v1/s/index-shard/3/transfer").is_empty());
        assert!(ask("swarmrec/v1/s/index-shard/3/x$*").is_empty());
        assert!(ask("swarmrec/v1/s/index-shard/4/query").is_empty()); // another robot's
        assert!(ask("not a //key").is_empty());
    }

    #[test]
    fn an_endpoint_declared_twice_is_refused() {
        let mut r: Routes<Asked> = Routes::new("s", "verifier", 0);
        r.add("verify", Box::new(|_| {})).unwrap();
        assert!(r.add("verify", Box::new(|_| {})).is_err());
    }
}
