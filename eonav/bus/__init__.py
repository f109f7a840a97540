"""The transport layer: the node skeleton every service uses (``node``), zenoh configuration from
flags (``session``) and an embedded router (``router``). Only services and the launcher import this
package; the math modules never do."""
