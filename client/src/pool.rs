//! The endpoints a [`crate::Client`] spreads its calls over, and which of them are down.
//!
//! One tonic `Channel` per endpoint (a `Channel` reconnects by itself on the call after its
//! connection broke), picked in turn among the endpoints not cooling down. An endpoint that failed
//! a call (unreachable, or UNAVAILABLE: overloaded, not ready, going away) cools down for 1 s,
//! doubled per failure in a row up to 10 s; then it is tried again, so a recovered endpoint comes
//! back with its next success. tonic's `Channel::balance_list` is not used: an endpoint whose
//! connection failed stays "ready" in it (the error waits for the next call), so a dead replica
//! kept its share of the calls, each of them failing once.

use std::{
    sync::{
        Mutex, MutexGuard,
        atomic::{AtomicUsize, Ordering},
    },
    time::{Duration, Instant},
};

use tonic::transport::{Channel, Endpoint};

use crate::Error;

/// How long an endpoint that failed is passed over, the first time in a row.
const COOLDOWN: Duration = Duration::from_secs(1);
/// The longest cool-down, however often it failed: it is probed at least this often.
const MAX_COOLDOWN: Duration = Duration::from_secs(10);

#[derive(Debug)]
pub(crate) struct Pool {
    replicas: Vec<Replica>,
    /// Whose turn it is, modulo the endpoints up.
    turn: AtomicUsize,
}

#[derive(Debug)]
struct Replica {
    name: String,
    channel: Channel,
    health: Mutex<Health>,
}

#[derive(Debug, Default)]
struct Health {
    /// Passed over until then, unless every endpoint is.
    down_until: Option<Instant>,
    /// The cool-down after the next failure (zero: the first).
    cooldown: Duration,
}

impl Health {
    fn is_down(&self, now: Instant) -> bool {
        self.down_until.is_some_and(|t| t > now)
    }
}

impl Pool {
    /// Endpoints connected on their first call.
    pub(crate) fn lazy(endpoints: Vec<(String, Endpoint)>) -> Pool {
        Pool::new(endpoints.into_iter().map(|(name, e)| (name, e.connect_lazy(), false)).collect())
    }

    /// Connects to every endpoint at once; those that cannot be reached are connected on a later
    /// call and start down. Fails only when none can be reached.
    pub(crate) async fn connect(endpoints: Vec<(String, Endpoint)>) -> Result<Pool, Error> {
        let mut connecting = tokio::task::JoinSet::new();
        for (i, (_, endpoint)) in endpoints.iter().enumerate() {
            let endpoint = endpoint.clone();
            connecting.spawn(async move { (i, endpoint.connect().await) });
        }
        let mut results: Vec<_> = endpoints.iter().map(|_| None).collect();
        while let Some(done) = connecting.join_next().await {
            let (i, result) = done.expect("connecting does not panic");
            results[i] = Some(result);
        }
        if results.iter().all(|r| matches!(r, Some(Err(_)))) {
            let names = endpoints.iter().map(|(name, _)| name.as_str()).collect::<Vec<_>>().join(", ");
            let Some(Some(Err(source))) = results.into_iter().next() else { unreachable!("all failed") };
            return Err(Error::Connect { endpoint: names, source });
        }
        let channels = endpoints
            .into_iter()
            .zip(results)
            .map(|((name, endpoint), result)| match result {
                Some(Ok(channel)) => (name, channel, false),
                _ => (name, endpoint.connect_lazy(), true),
            })
            .collect();
        Ok(Pool::new(channels))
    }

    /// Each endpoint's name, channel, and whether it starts down.
    fn new(channels: Vec<(String, Channel, bool)>) -> Pool {
        let replicas = channels
            .into_iter()
            .map(|(name, channel, down)| Replica { name, channel, health: Mutex::default() }.marked(down))
            .collect();
        Pool { replicas, turn: AtomicUsize::new(0) }
    }

    /// The endpoint for the next call: the next in turn among those up, or among all when every
    /// one is down (the caller has waited: one of them may be back).
    pub(crate) fn pick(&self) -> (usize, Channel) {
        let now = Instant::now();
        let up: Vec<usize> = (0..self.replicas.len()).filter(|&i| !self.replicas[i].health().is_down(now)).collect();
        let turn = self.turn.fetch_add(1, Ordering::Relaxed);
        let index = if up.is_empty() { turn % self.replicas.len() } else { up[turn % up.len()] };
        (index, self.replicas[index].channel.clone())
    }

    /// A call found the endpoint unreachable or unavailable: pass it over for a while. Calls that
    /// failed on it at the same time (it is already down) do not lengthen the cool-down.
    pub(crate) fn failed(&self, index: usize) {
        let now = Instant::now();
        let mut health = self.replicas[index].health();
        if health.is_down(now) {
            return;
        }
        let cooldown = if health.cooldown.is_zero() { COOLDOWN } else { health.cooldown };
        health.down_until = Some(now + cooldown);
        health.cooldown = (cooldown * 2).min(MAX_COOLDOWN);
    }

    /// The endpoint answered (whatever the answer): it is up, its next cool-down the first.
    pub(crate) fn answered(&self, index: usize) {
        *self.replicas[index].health() = Health::default();
    }

    pub(crate) fn any_up(&self) -> bool {
        let now = Instant::now();
        self.replicas.iter().any(|r| !r.health().is_down(now))
    }

    pub(crate) fn len(&self) -> usize {
        self.replicas.len()
    }

    /// The endpoints as given, for error messages.
    pub(crate) fn names(&self) -> String {
        self.replicas.iter().map(|r| r.name.as_str()).collect::<Vec<_>>().join(", ")
    }
}

impl Replica {
    fn health(&self) -> MutexGuard<'_, Health> {
        // Nothing panics while holding the lock; a poisoned one still holds valid data.
        self.health.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn marked(self, down: bool) -> Replica {
        if down {
            let mut health = self.health();
            health.down_until = Some(Instant::now() + COOLDOWN);
            health.cooldown = COOLDOWN * 2;
        }
        self
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pool(n: usize) -> Pool {
        let endpoints = (0..n)
            .map(|i| {
                let name = format!("127.0.0.1:{}", 1 + i);
                (name.clone(), Endpoint::from_shared(format!("http://{name}")).unwrap())
            })
            .collect();
        Pool::lazy(endpoints)
    }

    fn picks(pool: &Pool, n: usize) -> Vec<usize> {
        (0..n).map(|_| pool.pick().0).collect()
    }

    #[tokio::test]
    async fn turns_skip_endpoints_that_are_down_until_they_cool_down() {
        let pool = pool(3);
        assert_eq!(picks(&pool, 6), [0, 1, 2, 0, 1, 2]);
        pool.failed(1);
        assert!(picks(&pool, 6).iter().all(|&i| i != 1));
        assert!(pool.any_up());
        // Every endpoint down: they are all tried, in turn.
        pool.failed(0);
        pool.failed(2);
        assert!(!pool.any_up());
        let mut all = picks(&pool, 3);
        all.sort();
        assert_eq!(all, [0, 1, 2]);
        // An answer brings one back at once.
        pool.answered(2);
        assert_eq!(picks(&pool, 3), [2, 2, 2]);
        assert_eq!(pool.names(), "127.0.0.1:1, 127.0.0.1:2, 127.0.0.1:3");
    }

    #[tokio::test]
    async fn the_cooldown_doubles_per_failure_in_a_row_up_to_a_limit() {
        let pool = pool(1);
        let cooldowns = (0..6)
            .map(|_| {
                // The cool-down just ended: a fresh failure.
                pool.replicas[0].health().down_until = None;
                pool.failed(0);
                let until = pool.replicas[0].health().down_until.unwrap();
                (until - Instant::now()).as_secs_f64().round() as u64
            })
            .collect::<Vec<_>>();
        assert_eq!(cooldowns, [1, 2, 4, 8, 10, 10]);
        // Failures while it is down (concurrent calls) do not lengthen it.
        let until = pool.replicas[0].health().down_until;
        pool.failed(0);
        assert_eq!(pool.replicas[0].health().down_until, until);
        pool.answered(0);
        pool.failed(0);
        assert_eq!(pool.replicas[0].health().cooldown, COOLDOWN * 2, "an answer resets it");
    }
}
