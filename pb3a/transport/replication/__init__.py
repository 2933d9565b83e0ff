"""Remote links: an output's values replicated to other nodes over ZeroMQ PUB/SUB.

A ``Replicator`` sends the outputs of one process: each value is published once on
its output's topic, however many nodes (and inputs there) read it, and kept in a
bounded replay buffer. A ``Follower`` receives on one node: per sender, a SUB socket
for the topics it follows from it and a DEALER for the hand-shake and repairs, both
closed once no topic comes from that sender.

Every value carries (sender incarnation, topic, sequence number). Values published
while the previous ones are being sent travel together: small ones as one VALUES
message (first sequence number and count in its header, the values pickled as one
list: one seal, one send and one unpickling for up to ``BATCH_VALUES`` of them),
large ones (``ZERO_COPY_MIN`` bytes and more) each as a VALUE message whose payload
is a zero-copy frame, sealed on its own (below). The follower delivers each topic's
values in sequence order, exactly once:

- Slow joiners. A SUB socket misses what is published before its subscription
  reaches the publisher. So the follower says HELLO (topic, first sequence number
  it needs) on the DEALER until the publisher answers by publishing a SYNC on the
  topic; the first SYNC or value that arrives proves the subscription is live, and
  everything older is fetched from the replay buffer. No sleeping. Its first HELLO
  asks for that replay; the ones it repeats (every ``HELLO_EVERY``) say WAITING and
  are answered with a WELCOME and a SYNC only (in full by a publisher that never
  answered that follower: its first HELLO was lost), so a replay crossing a slow link
  is not sent again behind itself at each repeat. A replay not coming (nothing of it
  for as long as a repair waits, below) is asked again, in full. A follower whose
  subscription went live before it knew whom to name (see "Destinations") says LIVE
  in the HELLO naming the sender: nothing is replayed (PUB carries the values from
  then on; those before, it repairs as any gap); asking from where it was, it had the
  values PUB was carrying to it sent twice. (A live follow takes no WELCOME's next
  sequence number for a gap either: it comes ahead of values PUB still carries. Nor,
  once live, what the WELCOMEs answering its repeated HELLOs announced beyond the
  first message through its subscription: PUB carries those to it.)
- Gaps (the publisher's high-water mark dropped values for a slow follower, or a
  reconnect lost some) are repaired the same way; values beyond a gap wait; a
  heartbeat (SYNC every 0.5 s with the next sequence number) reveals values lost at
  the end of a burst. A repair re-sends whole messages: what of them was delivered
  already is counted as duplicates and dropped. What the replay buffer no longer
  holds is counted as a link failure, loudly. A repair not answered is asked again
  after ``REPAIR_RETRY_S``, then after twice as long each time (on a slow link the
  answer itself takes seconds to cross, and each request sends it again); each value
  or notice of an answer that comes over the control connection, duplicates of an
  earlier copy's too (and a WELCOME saying a replay follows), restarts the wait, and
  only the REPLAYED of the last request ends it.
- Flow control. Followers acknowledge (ACK) how far they are; a publisher more than
  ``WINDOW`` values or ``WINDOW_BYTES`` bytes ahead of its slowest live follower waits
  for it, briefly. The replay buffer holds twice the bytes of that window: everything
  a live follower may still need, and a bounded number of large values alive (the
  fewer, the warmer the memory the next one is copied into).
- Slow links. A dropping link (no lossless follower) slower than its writer must not
  queue at the writer: ZeroMQ counts its queue in messages, so large values piled up
  there by the hundred MiB and arrived ever later (tens of seconds). So the publisher
  keeps at most ``flight`` bytes on the way to its lead follower (the most advanced
  live one: a slower one beside it is not held to it): ``FLIGHT_START`` at first,
  doubled at each acknowledgement of a message that went less than ``FRESH_S / 2``
  ago, up to ``WINDOW_BYTES``. A value that does not fit waits for an acknowledgement
  while what is on the way is fresh; once the oldest of it went ``FRESH_S`` ago, or
  an acknowledgement comes that late, the link is *slow*: a message goes only when
  nothing is on the way, and the others are not sent (nor sealed, nor kept), without
  waiting. The values not sent are announced (SKIPPED before the next message that
  goes, a SYNC's count, a repair's answer): the follower counts them ``dropped`` and
  never asks for them. A link is not slow once a lone message is acknowledged within
  ``FRESH_S / 2``. So a `latest` reader gets a value about one message's crossing
  old, and the writer holds one message for the link. What a follower takes in over
  its control connection (its hand-shake's replay, or its repair of what its
  subscription missed before it knew whom to name) is not on the way over PUB: the
  flight counts from where PUB began to carry values to it
  (``stream.Stream.flight_lead``); counted from its ACKs, those values' age (they went
  long before) made the link slow.
- Slow followers. The flight follows the lead follower, and a PUB socket sends every
  message to every subscriber, queued per peer in messages: a slower follower beside
  a fast one had every value queued for it (hundreds of MiB, tens of seconds late),
  and flow control held the writer to it. So a live dropping follower behind another
  whose oldest message on the way went ``FRESH_S`` ago (once it has taken in what its
  hand-shake replayed: those went long ago) is served on its own (DIRECT):
  it closes its SUB connection (what PUB still queued for it is freed with it; an
  unsubscription would leave that queue to cross the slow link first) and counts the
  values it did not get before the switch dropped; once its ACK says it is served on
  its own (``SERVED_DIRECT``, below) the publisher sends it the newest message it does
  not have over its control connection whenever nothing sent to it there is on the
  way, the values before it announced not sent (SKIPPED); it leaves it out of flow
  control and of the flight from the switch on. Its queue at the ROUTER is bounded so
  (one message of values, small notices), and a ROUTER never blocks: it drops for a
  peer at its high-water mark (ROUTER_MANDATORY is not set). A DIRECT every heartbeat is its SYNC
  (how far it was sent) and says its mode again, also while it is silent (its link
  cut): it takes nothing over PUB until told RESUME. Once a lone message is acknowledged
  within ``FRESH_S / 2`` it goes back to PUB (RESUME): it subscribes, and what was
  published before its subscription took is counted dropped, not replayed. So does a
  live one once no live follower is served over PUB any more (the fast one unfollowed,
  was forgotten with its lost node, or has been silent for ``FOLLOWER_TIMEOUT``): at
  its next acknowledgement or the next heartbeat, whichever comes first, the most
  advanced of them (the others stay DIRECT beside it) goes back and leads, its link
  taken as slow (one message on the way at a time) until a lone message crosses in
  time. Left DIRECT, every value went to PUB for nobody and was kept, up to the replay
  buffer's bound. A silent one stays DIRECT until it is live again (a RESUME sent to a
  cut link may be lost). The RESUME goes behind what is on the way to it, which
  arrives; a repair it asked before it took the RESUME in is answered SKIPPED for the
  values before it (it counts them dropped), not replayed. Either switch may be lost
  on the way (a ROUTER drops what it sends to a peer whose connection is down), so
  each is said again until the two sides agree: a lost DIRECT at the next heartbeat
  (meanwhile the follower takes every value over PUB, and nothing is sent to it over
  its control connection: served there at an ordinary ACK past the switch, each such
  value crossed its slow link twice, a duplicate; told RESUME meanwhile, the fast one
  gone, it takes it in only if served on its own, and the publisher, no ACK having
  said it knew, takes it to be where its ACKs say, not at the RESUME's start: taken in,
  the values before that start still on their way over PUB were counted dropped, then
  arrived as duplicates); a lost RESUME at the follower's
  next ACK, which says it is served on its own
  (``SERVED_DIRECT``, one flag of the ACK: a wire change, both ends must run this
  version) while the publisher serves it over PUB: the publisher answers RESUME again,
  from the start the lost one said (one that crossed the ACK and was taken in says
  nothing new then), or, lossless, from where the ACK says it is. Without it, a
  follower whose RESUME was lost kept its SUB connection closed and waited on its
  control connection for values that all went to PUB: nothing more arrived, nor was
  counted, for as long as it followed.
- Lossless followers. A follower whose receiver must not drop (a ``lossless`` link)
  says so in its HELLO and ACKs, and acknowledges only what its receiver has put
  through. Such a follower holds the publisher back for as long as the writer's
  timeout allows (then the write fails: ``RuntimeTimeout``), and the replay buffer
  keeps every value it has not acknowledged; it stops holding when it says so, or
  when the link to it is cut (``release``).
- Fencing. A follower accepts one incarnation per topic. Values from any other (a
  sender that was migrated away, or a stale restart) are counted and dropped.
- Followers of lost nodes. A node's follower has one id at every replicator
  (``follower_id``: the node and its admission, its node epoch), by which acknowledgements
  and lossless holds are kept. When a reader's node is lost, the launcher asks the
  writer what that node's follower never acknowledged (``forget``): only its own
  acknowledgement counts (the least advanced follower's, a node lost earlier's left
  behind, said 1000 values lost of a node that had acknowledged them all). The follower
  is forgotten then: it holds nothing back, and what it says later (its node cut off,
  not dead) is refused, counted (``rejected["lost follower"]``). A node that rejoins
  has another id.
- Destinations. HELLO, REPAIR and ACK name the replicator they are for, by its
  incarnation (as control requests name their server's instance), so a copy captured
  on the wire and sent to another replicator within the freshness window is refused
  there (counted, ``rejected["other instance"]``), never taken as a follower's. A
  follower that does not know the incarnation yet (it learns it from the first
  WELCOME, SYNC or value) names nobody; such a HELLO is answered with a WELCOME and
  nothing else, and the follower says HELLO again at once, naming it.

Every message is sealed (``auth``) and opened before anything in it is decoded. A
large payload is sealed on its own at write time (``auth.Payloads``): encrypted with
AES-GCM straight from the writer's memory into the buffer that goes on the wire, one
pass that is both the copy value semantics need and the authentication, bound to what
it is (topic, incarnation, sequence number, kind, meta); its VALUE message carries the
payload's nonce and tag, which the message's own tag covers, so the message tag is
computed over a few dozen bytes instead of the whole payload again. The follower
decrypts it straight into where it lands (the reader's ring slot, when the receiver
offers one: ``land``), so checking and landing are one pass too; a payload whose tag
fails is refused and counted (``rejected["bad payload tag"]``) like any message, the
slot it was decrypted into is freed, and the gap is repaired like any lost message.
Only the next value in order lands in a slot (see ``_handle``). On this 2-core host
that took a 1 MiB array's CPU from about 530 us to about 500 (``bench/link_cpu.py``),
and the link from 0.65x to 0.80x raw pyzmq (``bench/local_link.py --remote``).

The package's modules: ``wire`` (the message kinds, their layouts, the numbers the
protocol runs by, and how a message is sent, received and sealed and its values
encoded), ``replicator`` (the sending side: ``Replicator`` and the state of each topic
it publishes) and ``follower`` (the receiving side: ``Follower``). Each imports the
numbers it reads by name, so a test that changes one patches the module that reads it
(``pb3a.transport.replication.replicator.WINDOW``, say); the numbers tests change are
not re-exported here, so that a patch of this package fails instead of doing nothing.
"""

from __future__ import annotations

from pb3a.transport.replication.follower import Follower
from pb3a.transport.replication.replicator import Replicator
from pb3a.transport.replication.wire import (
    ACK,
    ACK_EVERY,
    ANSWER,
    ASK,
    BATCH,
    BATCH_VALUES,
    DIRECT,
    HEARTBEAT_S,
    HELLO,
    INFO,
    LIVE,
    LOSSLESS,
    REPAIR,
    REPAIR_RETRY_S,
    REPLAYED,
    RESUME,
    SERVED_DIRECT,
    SILENT_S,
    SKIPPED,
    SYNC,
    VALUE,
    VALUES,
    WAITING,
    WELCOME,
    follower_id,
)

__all__ = [
    "ACK",
    "ACK_EVERY",
    "ANSWER",
    "ASK",
    "BATCH",
    "BATCH_VALUES",
    "DIRECT",
    "HEARTBEAT_S",
    "HELLO",
    "INFO",
    "LIVE",
    "LOSSLESS",
    "REPAIR",
    "REPAIR_RETRY_S",
    "REPLAYED",
    "RESUME",
    "SERVED_DIRECT",
    "SILENT_S",
    "SKIPPED",
    "SYNC",
    "VALUE",
    "VALUES",
    "WAITING",
    "WELCOME",
    "Follower",
    "Replicator",
    "follower_id",
]
