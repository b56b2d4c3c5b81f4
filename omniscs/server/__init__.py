"""The top-floor HTTP servers: HUGSIM's closed-loop protocol over the simulator (``omniscs.server.hugsim``). Like the
CLI they only wire requests to library calls; nothing below them imports them."""
