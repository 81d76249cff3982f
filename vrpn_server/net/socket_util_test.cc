#include "vrpn_server/net/socket_util.h"

#include <gtest/gtest.h>
#include <netinet/tcp.h>
#include <sys/socket.h>

namespace trackcal::vrpn {
namespace {

in_addr A(const char* s) { return *ParseIpv4(s); }

TEST(AllowList, Nominal) {
  const auto list = AllowList::Parse({"192.168.1.0/24", "10.0.0.7", "127.0.0.0/8"});
  EXPECT_TRUE(list.Allows(A("192.168.1.200")));
  EXPECT_FALSE(list.Allows(A("192.168.2.1")));
  EXPECT_TRUE(list.Allows(A("10.0.0.7")));
  EXPECT_FALSE(list.Allows(A("10.0.0.8")));
  EXPECT_TRUE(list.Allows(A("127.4.5.6")));
}

TEST(AllowList, EmptyAllowsEveryoneAndZeroLengthToo) {
  EXPECT_TRUE(AllowList::Parse({}).Allows(A("8.8.8.8")));
  EXPECT_TRUE(AllowList::Parse({"0.0.0.0/0"}).Allows(A("8.8.8.8")));
  // Host bits in the base are masked away.
  EXPECT_TRUE(AllowList::Parse({"192.168.1.77/24"}).Allows(A("192.168.1.1")));
}

TEST(AllowList, BadEntriesThrowNamingTheEntry) {
  for (const char* bad : {"192.168.1.0/33", "192.168.1/24", "host.example", "1.2.3.4/", "1.2.3.4/x"}) {
    try {
      AllowList::Parse({bad});
      ADD_FAILURE() << bad;
    } catch (const std::invalid_argument& e) {
      EXPECT_NE(std::string(e.what()).find(bad), std::string::npos);
    }
  }
}

TEST(ParseIpv4, RejectsNames) {
  EXPECT_TRUE(ParseIpv4("127.0.0.1"));
  EXPECT_FALSE(ParseIpv4("localhost"));
  EXPECT_FALSE(ParseIpv4("1.2.3.4.5"));
  EXPECT_EQ(FormatEndpoint(MakeSockaddr(A("1.2.3.4"), 3883)), "1.2.3.4:3883");
}

int IntOption(int fd, int level, int name) {
  int value = -1;
  socklen_t len = sizeof(value);
  EXPECT_EQ(::getsockopt(fd, level, name, &value, &len), 0);
  return value;
}

TEST(EnableDeadPeerDetection, ProbesAndUnacknowledgedDataAddUpToTheTimeout) {
  UniqueFd fd(::socket(AF_INET, SOCK_STREAM, 0));
  ASSERT_TRUE(fd.valid());
  EXPECT_EQ(IntOption(fd.get(), SOL_SOCKET, SO_KEEPALIVE), 0);  // the kernel's default
  ASSERT_TRUE(EnableDeadPeerDetection(fd.get(), 30.0));
  EXPECT_EQ(IntOption(fd.get(), SOL_SOCKET, SO_KEEPALIVE), 1);
  const int idle = IntOption(fd.get(), IPPROTO_TCP, TCP_KEEPIDLE);
  const int interval = IntOption(fd.get(), IPPROTO_TCP, TCP_KEEPINTVL);
  const int probes = IntOption(fd.get(), IPPROTO_TCP, TCP_KEEPCNT);
  // An idle dead peer is declared dead after idle + probes * interval seconds.
  EXPECT_EQ(idle + probes * interval, 30);
  EXPECT_EQ(IntOption(fd.get(), IPPROTO_TCP, TCP_USER_TIMEOUT), 30000);
  // Short timeouts keep whole-second probes of at least 1 s.
  ASSERT_TRUE(EnableDeadPeerDetection(fd.get(), 1.0));
  EXPECT_GE(IntOption(fd.get(), IPPROTO_TCP, TCP_KEEPINTVL), 1);
}

}  // namespace
}  // namespace trackcal::vrpn
